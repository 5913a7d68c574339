"""Array type aliases shared by the geometry modules."""

from __future__ import annotations

from typing import Any

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]
"""A float64 array; shapes and units are given where it is used."""

AnyArray = npt.NDArray[Any]
ArrayLike = npt.ArrayLike
