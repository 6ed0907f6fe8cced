"""Runs of the whole stack against the simulated hand, as tasks for tests and benches.

``campaign``: the fault campaign (every injector in every kind of phase, judged on the wire
and in the log); ``seed_run``: one run of a recipe on one perturbed simulated hand. Like
``session``, this is composition: the real runtime, bus and recorder with a simulated peer.
"""
