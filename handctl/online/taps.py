"""The directions a frame tap reports (``HandBus.tap``), in a module of their own so that the
recording writer process can read its rings without importing python-can (``handctl.online.bus``):
that import is a tenth of a second of every writer's start-up."""

from __future__ import annotations

TAP_RX = 0  # drained from the bus
TAP_TX = 1  # handed to the bus
TAP_TX_FAILED = 2  # refused by the bus (a bus event says why)
