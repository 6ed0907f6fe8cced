"""The numpy array type of handctl's signatures, defined here once so that every module (the
online plane, the recorder, the simulated hand) names the same type and none imports another
plane's module only to borrow it."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

#: A float64 array: angles (rad), torques (N·m), times (s) and the like.
FloatArray = npt.NDArray[np.float64]
#: A bool array: per joint, whether something holds of it.
BoolArray = npt.NDArray[np.bool_]
