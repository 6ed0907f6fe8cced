"""What ``handctl run recipe`` adds for the experiment on the simulated hand, beside the loop.

``merit``: the paper's figures of merit of a run, from ground truth recorded every tick (never
used for control); ``plot``: the overview picture of a run (and each phase's torque region,
for ``handctl plan --plot``). Nothing is imported here, so ``session`` stays light.
"""
