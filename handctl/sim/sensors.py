"""What the nodes measure: TDT joint-torque sensors and joint encoders, imperfect on purpose.

A host tested against perfect sensors learns nothing about plausibility checks, filters or
limits. The TDT model has a per-sensor constant bias drawn from the seed, white noise, a
first-order lag (sensor and analogue filter) and ADC quantisation; it reports on the wire in the
node's factory calibration, which the host undoes with the hand config's ``tdt.scale`` and
``tdt.offset``. Encoders quantise to their counts. Both saturate at the range of the wire
signals, as an ADC or a counter register would, rather than let the encoder refuse the frame.

Both models work on every joint of the hand in one call per 1 ms tick, on plain lists: for the
default hand's nine values a Python loop costs less than a dozen small NumPy calls, and the
readings go straight into the frame encoder as floats. Noise (with the bias folded in) comes
from a seeded generator in blocks of a thousand ticks, so a given seed always produces the same
readings.
"""

from __future__ import annotations

import math

import numpy as np

from handctl.config import HandConfig
from handctl.sim.params import NODE_TICK_S, EncoderParams, TdtParams

#: Largest magnitude an int16 signal of scale 0.0001 carries (N·m or rad).
WIRE_LIMIT = 3.2767
_NOISE_BLOCK = 1024


class TdtModel:
    """TDT readings of every joint, in config order, as they go on the wire (N·m)."""

    def __init__(self, hand: HandConfig, params: TdtParams, rng: np.random.Generator) -> None:
        n = hand.n_joints
        self.n = n
        self.params = params
        self._rng = rng
        self._alpha = 1.0 - math.exp(-NODE_TICK_S / params.lag) if params.lag > 0 else 1.0
        self.bias: list[float] = (
            rng.normal(0.0, params.bias, n).tolist() if params.bias > 0 else [0.0] * n
        )
        self._cal_offset = [j.tdt.offset for j in hand.joints]
        self._cal_inv_scale = [1.0 / j.tdt.scale for j in hand.joints]
        self._res = params.resolution
        self._inv_res = 1.0 / params.resolution if params.resolution > 0 else 0.0
        self._noise: list[list[float]] = []
        self._row = 0
        self.filtered: list[float] = [0.0] * n
        self.reading: list[float] = [0.0] * n
        # fault state, changed only by injectors (then ``update_faults``)
        self.stuck: list[bool] = [False] * n
        self.stuck_value: list[float] = [0.0] * n
        self.added: list[float] = [0.0] * n
        self._faulty = False

    def update_faults(self) -> None:
        """Injectors call this after changing ``stuck`` or ``added``: keeps the clean path lean."""
        self._faulty = any(self.stuck) or any(v != 0.0 for v in self.added)

    def _refill(self) -> None:
        block = self._rng.standard_normal((_NOISE_BLOCK, self.n))
        block *= self.params.noise
        block += np.asarray(self.bias)
        self._noise = block.tolist()
        self._row = 0

    def sample(self, transmitted: list[float]) -> list[float]:
        """One 1 ms sample of the torques the tendons transmit; returns ``reading``."""
        if self._row >= len(self._noise):
            self._refill()
        noise = self._noise[self._row]
        self._row += 1
        alpha = self._alpha
        filtered = self.filtered
        out = self.reading
        res, inv_res = self._res, self._inv_res
        offset, inv_scale = self._cal_offset, self._cal_inv_scale
        faulty = self._faulty
        lim = WIRE_LIMIT
        for i, x in enumerate(transmitted):
            f = filtered[i]
            f += alpha * (x - f)
            filtered[i] = f
            v = f + noise[i]
            if faulty:
                v += self.added[i]
            if inv_res:
                v = round(v * inv_res) * res
            # physical torque -> the node's factory calibration, as the host expects to undo it
            v = (v - offset[i]) * inv_scale[i]
            if v > lim:
                v = lim
            elif v < -lim:
                v = -lim
            if faulty and self.stuck[i]:
                v = self.stuck_value[i]
            out[i] = v
        return out


class EncoderModel:
    """Joint angles as the encoders report them (rad), quantised to whole counts."""

    def __init__(self, hand: HandConfig, params: EncoderParams) -> None:
        n = hand.n_joints
        self.params = params
        self.step = 2 * math.pi / params.counts_per_rev  # rad per count
        self._inv_step = 1.0 / self.step
        self.reading: list[float] = [0.0] * n
        self.jump: list[float] = [0.0] * n  # rad, set by the encoder_jump injector
        self._jumped = False

    def update_faults(self) -> None:
        self._jumped = any(v != 0.0 for v in self.jump)

    def sample(self, angles: list[float]) -> list[float]:
        """One sample of the true joint angles (rad); returns ``reading``."""
        step, inv = self.step, self._inv_step
        out = self.reading
        jumped = self._jumped
        lim = WIRE_LIMIT
        for i, q in enumerate(angles):
            v = round(q * inv) * step
            if jumped:
                v += self.jump[i]
            if v > lim:
                v = lim
            elif v < -lim:
                v = -lim
            out[i] = v
        return out
