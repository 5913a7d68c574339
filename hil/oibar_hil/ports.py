"""The six docking ports of our ISS-like target and their berthing-fixture frames.

Each port is given by the origin of its target frame F_t in LVLH (metres; station body frame =
LVLH, the station flies LVLH-hold) and by R_lvlh_t (columns: X_t, Y_t, Z_t in LVLH).
+Z_t points into the port, i.e. opposite to the approach side; +Y_t is chosen so that an aligned
camera sees the Earth towards the bottom of the image on V-bar ports, and +V-bar at the bottom
on R-bar ports. The table matches the approach axes of the paper's sequences (SPEC section 6).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .frames import APPROACH_NORMAL_LVLH

# Module stack along X (centre line y = z = 0): (name, x_min, x_max, radius) in metres.
MODULES_ALONG_X = (
    ("node_fwd", 12.0, 18.0, 2.2),
    ("lab", 2.0, 12.0, 2.1),
    ("node_mid", -4.0, 2.0, 2.2),
    ("fgb", -16.0, -4.0, 2.0),
    ("service", -28.0, -16.0, 2.0),
    ("service_aft", -31.0, -28.0, 1.5),
)
ADAPTER_LENGTH_M = 1.2  # docking adapter from module skin to the berthing plane


@dataclass(frozen=True)
class Port:
    number: int
    approach: str
    p_lvlh_t: np.ndarray  # target-frame origin in LVLH, m
    R_lvlh_t: np.ndarray  # F_t -> LVLH
    module_anchor_lvlh: np.ndarray  # where the adapter meets the module skin, m


def _axes_for(approach: str) -> np.ndarray:
    n = APPROACH_NORMAL_LVLH[approach]
    z_t = -n
    if approach in ("+V-bar", "-V-bar"):
        y_t = np.array([0.0, 0.0, 1.0])  # Earth (+R-bar) is image-down
    else:
        y_t = np.array([1.0, 0.0, 0.0])  # +V-bar is image-down
    x_t = np.cross(y_t, z_t)
    return np.stack([x_t, y_t, z_t], axis=1)


def _port(number: int, approach: str, anchor: tuple[float, float, float]) -> Port:
    a = np.array(anchor, dtype=float)
    n = APPROACH_NORMAL_LVLH[approach]
    return Port(number, approach, a + ADAPTER_LENGTH_M * n, _axes_for(approach), a)


PORTS = {
    1: _port(1, "+V-bar", (18.0, 0.0, 0.0)),  # forward end of the forward node
    2: _port(2, "-R-bar", (15.0, 0.0, -2.2)),  # zenith of the forward node
    3: _port(3, "-V-bar", (-31.0, 0.0, 0.0)),  # aft end of the service module
    4: _port(4, "-R-bar", (-10.0, 0.0, -2.0)),  # zenith of the FGB-like module
    5: _port(5, "+R-bar", (15.0, 0.0, 2.2)),  # nadir of the forward node
    6: _port(6, "+R-bar", (-22.0, 0.0, 2.0)),  # nadir of the service module
}
