"""handctl: grasp two objects with a joint-torque-controlled three-fingered hand over CAN."""

__version__ = "0.1.0"
