"""The berthing fixture as numbers: its dimensions, the corners of its rim and the keypoints the
pose estimator finds, all in the target frame F_t (metres).

F_t: origin at the centre of the berthing plane, +X right and +Y down for an aligned camera,
+Z into the port; the rim's front face is at z = 0 and the plate face is recessed behind it.
Sizes are ours (the paper scales its CAD up to fit the ATV/ISS): assumptions collected in
:class:`FixtureDims`. The simulator's meshes (oibar_hil.meshes) are built from these numbers.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ._types import FloatArray


@dataclass(frozen=True)
class FixtureDims:
    """Dimensions of the berthing fixture, metres, in F_t."""

    width_m: float = 0.50  # along X_t (outer rectangle)
    height_m: float = 0.36  # along Y_t
    rim_width_m: float = 0.03
    rim_depth_m: float = 0.02  # rim front face at z = 0, plate face recessed behind it
    plate_thickness_m: float = 0.03
    drogue_mouth_radius_m: float = 0.095
    drogue_throat_radius_m: float = 0.025
    drogue_depth_m: float = 0.16
    pin_guide_x_m: float = 0.17
    pin_guide_radius_m: float = 0.035
    couplings_xy_m: tuple[tuple[float, float], ...] = ((-0.10, 0.115), (0.10, 0.115))
    coupling_radius_m: float = 0.024
    connector_xy_m: tuple[float, float] = (0.0, -0.115)
    connector_size_m: tuple[float, float] = (0.09, 0.04)


FIXTURE = FixtureDims()


def fixture_corners_t(d: FixtureDims = FIXTURE) -> FloatArray:
    """The four corners of the rectangular rim in F_t (z = 0), metres, in image order for an
    aligned camera: top-left, top-right, bottom-right, bottom-left."""
    w, h = d.width_m / 2, d.height_m / 2
    return np.array([[-w, -h, 0.0], [w, -h, 0.0], [w, h, 0.0], [-w, h, 0.0]])


FIXTURE_KEYPOINTS: tuple[tuple[str, tuple[float, float, float]], ...] = (
    ("rim_top_left", (-0.25, -0.18, 0.0)),
    ("rim_top_right", (0.25, -0.18, 0.0)),
    ("rim_bottom_right", (0.25, 0.18, 0.0)),
    ("rim_bottom_left", (-0.25, 0.18, 0.0)),
    ("pin_guide_left", (-0.17, 0.0, 0.005)),
    ("pin_guide_right", (0.17, 0.0, 0.005)),
    ("coupling_left", (-0.10, 0.115, 0.002)),
    ("coupling_right", (0.10, 0.115, 0.002)),
    ("connector_top_left", (-0.045, -0.135, 0.0045)),
    ("connector_top_right", (0.045, -0.135, 0.0045)),
    ("connector_bottom_right", (0.045, -0.095, 0.0045)),
    ("connector_bottom_left", (-0.045, -0.095, 0.0045)),
    ("drogue_centre", (0.0, 0.0, 0.012)),
    ("drogue_throat", (0.0, 0.0, 0.18)),
)
"""The keypoints of the keypoint pose estimator: (name, (x, y, z) in F_t, metres) of the default
fixture (:data:`FIXTURE`): rim corners, pin-guide boss centres, coupling centres, connector
corners and the drogue's outer lip centre (front faces, all within 12 mm of one plane), and the
drogue's throat 0.18 m deep, the one point whose image moves with tilt (model 0.5.0 on; earlier
models carry the first 13). Written out as literals because the shipped models carry them bit
for bit; tests/host/test_geometry.py checks them against FixtureDims."""

KEYPOINT_VIEW_LIMIT_DEG: dict[str, float] = {"drogue_throat": 25.0}
"""Keypoints seen only within a cone around the fixture's outward axis (-Z_t): the throat's
centre, 0.169 m behind the 95 mm-radius mouth, shows through it up to atan(0.095 / 0.169) = 29 deg;
25 keeps the training labels off the funnel's lip."""


def keypoints_m() -> FloatArray:
    """(K, 3) the positions of :data:`FIXTURE_KEYPOINTS`, metres in F_t."""
    return np.array([p for _, p in FIXTURE_KEYPOINTS], float)


def _circle(center: tuple[float, float, float], radius_m: float, segments: int) -> FloatArray:
    a = np.linspace(0.0, 2.0 * np.pi, segments + 1)
    pts = np.stack(
        [center[0] + radius_m * np.cos(a), center[1] + radius_m * np.sin(a), np.full_like(a, center[2])],
        axis=1,
    )
    return np.stack([pts[:-1], pts[1:]], axis=1)


def _rectangle(cx: float, cy: float, w: float, h: float, z: float) -> FloatArray:
    c = np.array(
        [
            [cx - w / 2, cy - h / 2, z],
            [cx + w / 2, cy - h / 2, z],
            [cx + w / 2, cy + h / 2, z],
            [cx - w / 2, cy + h / 2, z],
        ]
    )
    return np.stack([c, np.roll(c, -1, axis=0)], axis=1)


def fixture_wireframe_t(d: FixtureDims = FIXTURE, segments: int = 32) -> FloatArray:
    """(E, 2, 3) line segments in F_t (metres) outlining the fixture's visible features for
    overlays: the rim's outer and inner rectangles at both faces, the drogue's mouth and throat,
    the pin-guide bosses, the couplings and the connector. A drawing aid, not the rendered mesh."""
    zp = d.rim_depth_m
    segs = [
        _rectangle(0.0, 0.0, d.width_m, d.height_m, 0.0),
        _rectangle(0.0, 0.0, d.width_m, d.height_m, zp),
        _rectangle(0.0, 0.0, d.width_m - 2 * d.rim_width_m, d.height_m - 2 * d.rim_width_m, 0.0),
        _circle((0.0, 0.0, zp), d.drogue_mouth_radius_m, segments),
        _circle((0.0, 0.0, zp + d.drogue_depth_m), d.drogue_throat_radius_m, segments),
    ]
    corners = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]], float) * [d.width_m / 2, d.height_m / 2]
    segs.append(np.stack([np.c_[corners, np.zeros(4)], np.c_[corners, np.full(4, zp)]], axis=1))
    for sx in (-1.0, 1.0):
        segs.append(_circle((sx * d.pin_guide_x_m, 0.0, zp - 0.015), d.pin_guide_radius_m, segments))
    for x, y in d.couplings_xy_m:
        segs.append(_circle((x, y, 0.002), d.coupling_radius_m, segments))
    cx, cy = d.connector_xy_m
    segs.append(_rectangle(cx, cy, d.connector_size_m[0], d.connector_size_m[1], zp - 0.0155))
    return np.concatenate(segs).astype(float)
