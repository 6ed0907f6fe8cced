"""Offline analysis (paper §3–§4): rolling-contact kinematics and robust torque sets.

Given a grasp of several objects enveloped by several fingers, this package answers the
question every manipulation phase of a recipe asks: *which joint torques are guaranteed to move
each object the wanted way, whatever the (non-unique) contact forces turn out to be?*

Modules, each depending only on those above it:

* ``frames`` — rotations and the vector-product operators of eqs. 5–7 (2D trap explained there).
* ``model`` — objects, fingers, contacts, friction; strict YAML loading of scenario files.
* ``kinematics`` — ``J_jk``, ``D_F`` and ``D_B`` of eqs. 1–9, in 2D and 3D.
* ``statics`` — ``V``, ``J``, ``D_CB``, ``D_O``, ``M_B``, ``h_B``, eqs. 10–22 as affine maps of λ.
* ``conditions`` — eqs. 23–24 as linear conditions; why eq. 24 is replaced, and gravity.
* ``polygons`` — convex polygon clipping and distances for the exact sets.
* ``slices`` — two-parameter torque planes, eq. 25.
* ``oracle`` — the LP oracle: one LP per condition and torque (HiGHS).
* ``exact`` — the exact polyhedral torque set from the dual LPs' vertices.
* ``planner`` — torques with the largest robust margin (a small MILP, checked by the oracle).
* ``plot`` — Fig. 3-style PNG (matplotlib, imported lazily).
* ``commands`` — ``torque_set_report`` behind ``handctl analyze torque-set``.

The offline plane only: the online loop never imports this package.
"""

from handctl.analysis.commands import torque_set_report
from handctl.analysis.conditions import Conditions, build_conditions
from handctl.analysis.exact import ExactTorqueSet, exact_torque_set
from handctl.analysis.model import AnalysisError, Grasp, Scenario, load_scenario
from handctl.analysis.planner import TorquePlan, plan_for_conditions, plan_torques
from handctl.analysis.slices import TorqueSlice, ratio_slice

__all__ = [
    "AnalysisError",
    "Conditions",
    "ExactTorqueSet",
    "Grasp",
    "Scenario",
    "TorquePlan",
    "TorqueSlice",
    "build_conditions",
    "exact_torque_set",
    "load_scenario",
    "plan_for_conditions",
    "plan_torques",
    "ratio_slice",
    "torque_set_report",
]
