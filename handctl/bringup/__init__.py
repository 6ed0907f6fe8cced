"""Bring-up of a hand: list its nodes, watch the bus decoded, calibrate the TDT sensors, jog a
joint. The listening commands never send; the others run through the Runtime and the safety
supervisor like any recipe (docs/bringup.md)."""
