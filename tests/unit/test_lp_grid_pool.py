"""The analysis' LP grid as row tasks: the same masks on a pool of worker processes as here,
row for row in order."""

from __future__ import annotations

import io

import numpy as np

from handctl.analysis.conditions import build_conditions
from handctl.analysis.model import load_scenario
from handctl.analysis.oracle import lp_grid
from handctl.analysis.slices import ratio_slice
from handctl.executor import open_pool
from handctl.progress import Progress

from ..conftest import ROOT

FIG3 = ROOT / "config" / "analysis" / "paper_fig3.yaml"


def test_lp_grid_on_a_pool_equals_the_grid_here() -> None:
    sc = load_scenario(FIG3)
    cond = build_conditions(sc.grasp, sc.directions)
    sl = ratio_slice(sc.grasp, (0.9, 0.1), sc.tau_max)
    lo, hi = sl.bounds()
    xs, ys = np.linspace(lo[0], hi[0], 13), np.linspace(lo[1], hi[1], 11)
    real, inside = lp_grid(cond, sl, xs, ys)
    out = io.StringIO()
    with open_pool(2) as pool, Progress("rows", len(ys), stream=out, terminal=False) as bar:
        real_pool, inside_pool = lp_grid(cond, sl, xs, ys, pool, bar)
    assert real.shape == inside.shape == (11, 13)
    assert np.array_equal(real, real_pool) and np.array_equal(inside, inside_pool)
    assert inside.any() and (~real).any()  # rows differ: an order mix-up would show
    assert out.getvalue().splitlines()[-1].startswith("rows: 11/11 in ")
