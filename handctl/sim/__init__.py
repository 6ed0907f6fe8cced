"""The simulated hand: a MuJoCo hand of the config's shape and its objects behind emulated CAN
nodes.

It is a peer on the bus and nothing more: the online plane never imports this package, and the
host cannot tell it from the real hand by its frames. Modules, each depending only on those
before it:

- ``placement``: whether the scene can start (names, reach, nothing inside anything else);
- ``params``: the ``sim:`` section of the hand config (every physical number, SI units);
- ``plant``: the MuJoCo model built from the config, stepped one 1 ms node tick at a time;
- ``sensors``: TDT torque sensors and encoders with noise, bias, lag and quantisation;
- ``firmware``: one finger's controller node as ``firmware_protocol/PROTOCOL.md`` specifies it;
- ``faults``: fault injectors and the scenario files that switch them in time;
- ``hand``: ``SimulatedHand`` (lockstep ``step()`` or free-running ``start()``/``stop()``) and
  ``standalone`` for ``handctl sim --bus SPEC``;
- ``render``: a drawing of the scene, for checking a configuration by eye.
"""
