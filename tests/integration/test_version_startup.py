"""A run refuses, at start-up, a node that speaks another protocol version: nothing is sent."""

from __future__ import annotations

import pytest

from handctl.config import HandConfig
from handctl.online.loop import Outcome
from handctl.online.safety.faults import FaultCode

from .rig import rig


@pytest.mark.parametrize("version", [1, 3])
def test_a_node_of_another_version_fails_the_start_up(hand: HandConfig, version: int) -> None:
    with rig(hand, None, max_seconds=1.0) as r:
        r.sim.nodes[1].protocol_version = version
        result = r.run()
    assert result.outcome is Outcome.STARTUP_FAILED
    assert f"node 2 (f2) speaks handctl protocol {version}, this host protocol 2" in result.message
    assert [f.code for f in result.faults] == [FaultCode.STARTUP]
    host_ids = {0x000, 0x011, 0x012, 0x013, 0x101, 0x102, 0x103}
    assert not [fid for fid, _ in r.wire if fid in host_ids]  # the host sent nothing


def test_nodes_of_the_host_s_version_start(hand: HandConfig) -> None:
    with rig(hand, None, max_seconds=0.05) as r:
        result = r.run()
    assert result.outcome is not Outcome.STARTUP_FAILED, result.message
