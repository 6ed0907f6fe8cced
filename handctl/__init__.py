"""handctl: grasp, lift and manipulate objects with a joint-torque-controlled hand over CAN."""

__version__ = "0.1.0"
