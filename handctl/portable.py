"""A hand config as data a worker process can receive (pickled, on this machine or another).

``HandConfig.sim`` is a read-only mapping proxy, which does not pickle; everything else in a
hand config is plain frozen data. A task carries ``portable_hand(hand)`` (the same config with
``sim`` a plain dict) and the worker turns it back with ``local_hand`` before using it, so code
that relies on ``sim`` being read-only keeps that guarantee on either side.
"""

from __future__ import annotations

import dataclasses
from types import MappingProxyType

from handctl.config import HandConfig


def portable_hand(hand: HandConfig) -> HandConfig:
    """``hand`` with its ``sim`` section as a plain dict (picklable)."""
    return dataclasses.replace(hand, sim=dict(hand.sim))


def local_hand(hand: HandConfig) -> HandConfig:
    """A received ``portable_hand`` with its ``sim`` section read-only again."""
    return dataclasses.replace(hand, sim=MappingProxyType(dict(hand.sim)))
