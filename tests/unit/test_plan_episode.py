"""The planner's episodes on hands of other shapes than the default: one object is no pair."""

from __future__ import annotations

from handctl.config import load_hand
from handctl.online.recipes.schema import Phase, RecipeObject, TimeoutAction
from handctl.planning.episode import Episode
from handctl.sim.params import parse_sim

from ..conftest import ROOT

FOUR_BY_FOUR = ROOT / "config" / "hands" / "four_fingers_four_joints.yaml"


def test_a_phase_on_one_object_has_no_pair_to_block() -> None:
    """The four-by-four hand holds one cylinder: a phase ends with no pair blocked, no pair
    gap and no turn (the hold scorer asks whether a link lies between the pair's objects)."""
    hand = load_hand(FOUR_BY_FOUR)
    params = parse_sim(hand)
    (cylinder,) = params.objects
    episode = Episode(hand, params, [RecipeObject(cylinder.name, cylinder.radius)])
    phase = Phase("hold", (0.0,) * hand.n_joints, 0.0, 0.05, TimeoutAction.NEXT, (), ())
    outcome = episode.run_phase(phase)
    assert outcome.exit == "timeout"
    assert outcome.pair_blocked is False
    assert outcome.pair_gap == 0.0 and outcome.true_turn_deg == 0.0
