"""The fault campaign's cases as tasks: the same results on a pool of worker processes as
here, in the campaign's order, with each case's log brought back from its worker."""

from __future__ import annotations

from pathlib import Path

from handctl.config import HandConfig
from handctl.executor import open_pool
from handctl.harness.campaign import PHASES, read_case_log, run_campaign


def test_cases_on_a_pool_equal_the_cases_here(hand: HandConfig, tmp_path: Path) -> None:
    injectors = ["tdt_offset"]
    here = run_campaign(hand, injectors=injectors)
    lines: list[str] = []
    with open_pool(2) as pool:
        there = run_campaign(
            hand, progress=lines.append, injectors=injectors, log_dir=tmp_path, executor=pool
        )
    assert there == here
    assert [(r.injector, r.phase) for r in there] == [(i, p) for i in injectors for p, _ in PHASES]
    assert len(lines) == len(there) and lines[0].startswith("tdt_offset")
    for r in there:
        log = read_case_log(tmp_path / f"{r.injector}-{r.phase}.mcap")
        assert r.logged
        assert log.complete and bool(log.faults) == bool(r.fault)
