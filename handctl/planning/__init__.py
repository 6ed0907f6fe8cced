"""Offline planning of a recipe on the simulated hand (``handctl plan``).

The analysis (``handctl.analysis``) answers, for one grasp configuration, which torques are
guaranteed to move each object the wanted way; this package supplies what it needs and what it
cannot know: the configuration of every phase (by running the phases before it on the
simulated hand), a search that refines the torques where the quasi-static condition is empty
or too conservative, scored over perturbed models, and the compiled recipe with its provenance.

Modules: ``models`` (perturbed models), ``episode`` (a phase on one model, no bus), ``grasp``
(the analysis' ``Grasp`` from a simulated configuration), ``template`` (the plan's input),
``search`` (the per-phase search), ``compile`` (the whole plan and the recipe it writes).
A plan's pictures (``plan --plot``) are drawn by ``handctl.experiment.plot``.

The offline plane: it imports the simulation and the analysis, and the online plane never
imports it.
"""
