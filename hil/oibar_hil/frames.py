"""Reference frames.

LVLH (local vertical, local horizontal) in the ISS/NASA convention, centred on the target:
  +X  V-bar: along the orbital velocity (for a circular orbit exactly the velocity direction),
  +Z  R-bar: from the target towards the centre of the Earth (nadir),
  +Y  H-bar: along the *negative* orbit normal, completing the right-handed triad.
Other tools (e.g. Hill/CW with x radial outwards) use other axes; always convert explicitly.

Approach names follow the side the chaser comes from: a "+V-bar approach" has the chaser on the
+X side moving in -X; "-R-bar" has it on the -Z (zenith) side looking down towards the Earth;
"+R-bar" has it on the +Z (nadir) side looking up into space.

The target (station) flies LVLH-hold, so its body frame is the LVLH frame.
"""

from __future__ import annotations

import numpy as np


def lvlh_rotation(r_eci: np.ndarray, v_eci: np.ndarray) -> np.ndarray:
    """R_eci_lvlh: columns are the LVLH axes expressed in the inertial frame of r and v."""
    r = np.asarray(r_eci, dtype=float)
    v = np.asarray(v_eci, dtype=float)
    z = -r / np.linalg.norm(r)
    h = np.cross(r, v)
    y = -h / np.linalg.norm(h)
    x = np.cross(y, z)
    return np.stack([x, y, z], axis=1)


def eci_to_lvlh(vec_eci: np.ndarray, r_eci: np.ndarray, v_eci: np.ndarray) -> np.ndarray:
    return lvlh_rotation(r_eci, v_eci).T @ np.asarray(vec_eci, dtype=float)


# Outward port normal (the side the chaser comes from), LVLH, per approach name.
APPROACH_NORMAL_LVLH = {
    "+V-bar": np.array([1.0, 0.0, 0.0]),
    "-V-bar": np.array([-1.0, 0.0, 0.0]),
    "+R-bar": np.array([0.0, 0.0, 1.0]),
    "-R-bar": np.array([0.0, 0.0, -1.0]),
}
