"""The suite's units of work on xdist's workers (``tests/worker_units.py``): a module stays
together, a marked group leaves its modules and stays together across them."""

from __future__ import annotations

import pytest

from ..worker_units import ModuleOrGroupScheduling


@pytest.fixture
def scheduling() -> ModuleOrGroupScheduling:
    """A scheduler without the controller's state (workers, collections): splitting node ids
    into units needs none of it, and its constructor wants the controller's ``-n``."""
    return ModuleOrGroupScheduling.__new__(ModuleOrGroupScheduling)


def test_the_tests_of_a_module_are_one_unit(scheduling: ModuleOrGroupScheduling) -> None:
    units = {
        scheduling._split_scope(nodeid)
        for nodeid in (
            "tests/integration/test_x.py::test_a",
            "tests/integration/test_x.py::test_b[k0]",
            "tests/integration/test_x.py::test_b[k1]",
        )
    }
    assert units == {"tests/integration/test_x.py"}


def test_a_group_is_one_unit_across_modules(scheduling: ModuleOrGroupScheduling) -> None:
    """xdist appends ``@NAME`` to the node id of a test marked ``xdist_group(NAME)``."""
    units = [
        scheduling._split_scope(nodeid)
        for nodeid in (
            "tests/integration/test_x.py::test_a@realtime",
            "tests/integration/test_y.py::test_b[k0]@realtime",
            "tests/integration/test_x.py::test_c",
        )
    ]
    assert units == ["realtime", "realtime", "tests/integration/test_x.py"]


def test_an_at_sign_in_a_parameter_is_not_a_group(scheduling: ModuleOrGroupScheduling) -> None:
    nodeid = "tests/unit/test_x.py::test_a[user@host]"
    assert scheduling._split_scope(nodeid) == "tests/unit/test_x.py"
