"""Meshes built in code (trimesh, manifold3d for booleans): the berthing fixture, the
end-effector, and an ISS-like station with six ports. Nothing is downloaded.

Fixture geometry is in the target frame F_t (see trajectory.py): front face of the rectangular
boundary at z = 0, +Z into the port. Its dimensions are numbers in oibar.geometry.fixture
(FixtureDims), shared with the pose estimator's keypoints and the lab toolbox's overlay.
"""

from __future__ import annotations

from dataclasses import dataclass

import manifold3d as mf
import numpy as np
import trimesh

from oibar.geometry.fixture import FIXTURE, FixtureDims

from .ports import ADAPTER_LENGTH_M, MODULES_ALONG_X, PORTS, Port

# Part ids (also the value written by the renderer's id pass).
ID_BOUNDARY = 1  # rectangular boundary (rim) of the berthing plate
ID_PLATE = 2
ID_DROGUE = 3
ID_PIN_GUIDE = 4
ID_COUPLING = 5
ID_CONNECTOR = 6
ID_ADAPTER = 7
ID_MODULE = 10
ID_TRUSS = 11
ID_RADIATOR = 12
ID_SOLAR_ARRAY = 13
ID_OTHER_FIXTURE = 14
ID_END_EFFECTOR = 20


# ----------------------------------------------------------------------------- primitives
SEGMENTS = 40


def _to_trimesh(m: mf.Manifold) -> trimesh.Trimesh:
    mesh = m.to_mesh()
    return trimesh.Trimesh(
        vertices=np.asarray(mesh.vert_properties)[:, :3], faces=np.asarray(mesh.tri_verts), process=False
    )


def _box(size, center) -> mf.Manifold:
    return mf.Manifold.cube(tuple(size), center=True).translate(tuple(center))


def _frustum(
    r0: float, r1: float, z0: float, z1: float, xy=(0.0, 0.0), segments: int = SEGMENTS
) -> mf.Manifold:
    """Solid cone frustum along +Z from z0 (radius r0) to z1 (radius r1)."""
    return mf.Manifold.cylinder(z1 - z0, r0, r1, segments).translate((xy[0], xy[1], z0))


@dataclass
class Part:
    mesh: trimesh.Trimesh
    rgb: tuple
    specular: float
    part_id: int
    # which part of the fixture this is (rim, plate, ...): the key of its material in a
    # randomised look (oibar_hil.randomize); empty for the station's parts
    name: str = ""


# ----------------------------------------------------------------------------- fixture
def drogue_envelope(d: FixtureDims = FIXTURE) -> mf.Manifold:
    """The drogue funnel's outside: what a port adapter behind the fixture must leave free."""
    r_m, r_t = d.drogue_mouth_radius_m, d.drogue_throat_radius_m
    return _frustum(r_m + 0.02, r_t + 0.02, d.rim_depth_m - 0.008, d.rim_depth_m + d.drogue_depth_m + 0.08)


def berthing_fixture(d: FixtureDims = FIXTURE) -> list[Part]:
    w, h = d.width_m, d.height_m
    z_plate0 = d.rim_depth_m
    z_plate1 = z_plate0 + d.plate_thickness_m

    rim = _box((w, h, d.rim_depth_m), (0, 0, d.rim_depth_m / 2)) - _box(
        (w - 2 * d.rim_width_m, h - 2 * d.rim_width_m, 1.0), (0, 0, 0)
    )

    plate = _box((w, h, d.plate_thickness_m), (0, 0, (z_plate0 + z_plate1) / 2))
    plate = plate - _frustum(d.drogue_mouth_radius_m, d.drogue_mouth_radius_m, -0.1, 0.2)
    guide_cuts = []
    for sx in (-1, 1):
        xy = (sx * d.pin_guide_x_m, 0.0)
        # Tapered cavity for the alignment pins: wide at the mouth, narrow inside.
        guide_cuts.append(_frustum(0.024, 0.010, z_plate0 - 0.016, z_plate1 + 0.001, xy))
    cut = guide_cuts[0] + guide_cuts[1]
    plate = plate - cut
    bosses = None
    for sx in (-1, 1):
        b = _frustum(
            d.pin_guide_radius_m,
            d.pin_guide_radius_m,
            z_plate0 - 0.015,
            z_plate0 + 0.001,
            (sx * d.pin_guide_x_m, 0.0),
        )
        bosses = b if bosses is None else bosses + b
    bosses = bosses - cut

    # Drogue funnel: a cone shell behind the plate, lip flush with the plate face.
    r_m, r_t, depth = d.drogue_mouth_radius_m, d.drogue_throat_radius_m, d.drogue_depth_m
    outer = drogue_envelope(d)
    inner = _frustum(r_m, r_t, z_plate0 - 0.009, z_plate0 + depth) + _frustum(
        r_t, r_t, z_plate0 + depth - 0.001, z_plate0 + depth + 0.06
    )
    drogue = outer - inner
    # The latch bore at the funnel's bottom: a dark opening (no light reaches down a 5 cm hole;
    # the rasteriser has no occlusion term, so it is given a dark material). It marks the throat,
    # the fixture's one deep keypoint (FIXTURE_KEYPOINTS' drogue_throat, 0.18 m), where the image
    # shows it: lit like the funnel, the throat had no feature of its own and keypoint networks
    # learned the funnel's centre instead, which is the same point only when seen from the axis.
    bore = _frustum(r_t, r_t, z_plate0 + depth, z_plate0 + depth + 0.004)

    couplings = None
    for x, y in d.couplings_xy_m:
        c = _frustum(d.coupling_radius_m, d.coupling_radius_m, 0.002, z_plate0 + 0.001, (x, y)) - _frustum(
            0.010, 0.010, 0.0, 0.014, (x, y)
        )
        couplings = c if couplings is None else couplings + c

    cx, cy = d.connector_xy_m
    sx_, sy_ = d.connector_size_m
    connector = _box((sx_, sy_, 0.016), (cx, cy, z_plate0 - 0.008 + 0.0005))
    for i in range(4):
        connector = connector - _box((0.010, 0.012, 0.02), (cx - 0.03 + 0.02 * i, cy, 0.0))

    return [
        Part(_to_trimesh(rim), (0.10, 0.10, 0.12), 0.3, ID_BOUNDARY, "rim"),
        Part(_to_trimesh(plate), (0.72, 0.72, 0.75), 0.6, ID_PLATE, "plate"),
        Part(_to_trimesh(bosses), (0.70, 0.50, 0.28), 0.5, ID_PIN_GUIDE, "pin_guides"),
        Part(_to_trimesh(drogue), (0.82, 0.82, 0.85), 0.8, ID_DROGUE, "drogue"),
        Part(_to_trimesh(bore), (0.03, 0.03, 0.035), 0.05, ID_DROGUE, "bore"),
        Part(_to_trimesh(couplings), (0.85, 0.65, 0.22), 0.7, ID_COUPLING, "couplings"),
        Part(_to_trimesh(connector), (0.06, 0.06, 0.07), 0.2, ID_CONNECTOR, "connector"),
    ]


def end_effector() -> list[Part]:
    """The chaser's end-effector in F_s (shaft plane at z = 0, probe pointing +Z towards the
    target): body, fluidic plane with alignment pins and couplings, spring probe with latch
    head. Not drawn by the camera renderer (the camera rides on it); kept for the HIL rig."""
    body = _frustum(0.16, 0.16, -0.30, -0.05, segments=48)
    fluidic = _box((0.44, 0.30, 0.03), (0, 0, -0.035))
    pins = None
    for sx in (-1, 1):
        pin = _frustum(0.012, 0.006, -0.02, 0.05, (sx * 0.17, 0.0))
        pins = pin if pins is None else pins + pin
    probe = _frustum(0.022, 0.022, -0.02, 0.22) + _frustum(0.022, 0.004, 0.22, 0.27)
    latches = _box((0.06, 0.01, 0.02), (0, 0, 0.20))
    return [
        Part(_to_trimesh(body), (0.75, 0.75, 0.78), 0.5, ID_END_EFFECTOR),
        Part(_to_trimesh(fluidic), (0.65, 0.66, 0.70), 0.6, ID_END_EFFECTOR),
        Part(_to_trimesh(pins), (0.70, 0.50, 0.28), 0.5, ID_END_EFFECTOR),
        Part(_to_trimesh(probe + latches), (0.85, 0.85, 0.88), 0.8, ID_END_EFFECTOR),
    ]


# ----------------------------------------------------------------------------- station
def _cyl_x(x0, x1, r, y=0.0, z=0.0, segments=32) -> trimesh.Trimesh:
    m = _to_trimesh(_frustum(r, r, x0, x1, segments=segments))
    # Cylinder along +Z -> along +X.
    T = np.array([[0, 0, 1, 0], [1, 0, 0, y], [0, 1, 0, z], [0, 0, 0, 1]], dtype=float)
    return m.apply_transform(T)


def _cyl_y(y0, y1, r, x=0.0, z=0.0, segments=32) -> trimesh.Trimesh:
    m = _to_trimesh(_frustum(r, r, y0, y1, segments=segments))
    T = np.array([[0, 1, 0, x], [0, 0, 1, 0], [1, 0, 0, z], [0, 0, 0, 1]], dtype=float)
    return m.apply_transform(T)


def _tbox(size, center) -> trimesh.Trimesh:
    return trimesh.creation.box(extents=size, transform=trimesh.transformations.translation_matrix(center))


def _truss(
    x_c: float, z_c: float, y0: float, y1: float, side: float = 3.0, bay: float = 4.0, beam: float = 0.14
):
    parts = []
    hs = side / 2
    for dx in (-hs, hs):
        for dz in (-hs, hs):
            parts.append(_tbox((beam, y1 - y0, beam), (x_c + dx, (y0 + y1) / 2, z_c + dz)))
    n_bays = int(round((y1 - y0) / bay))
    for i in range(n_bays + 1):
        y = y0 + i * (y1 - y0) / n_bays
        parts.append(_tbox((side, beam, beam), (x_c, y, z_c - hs)))
        parts.append(_tbox((side, beam, beam), (x_c, y, z_c + hs)))
        parts.append(_tbox((beam, beam, side), (x_c - hs, y, z_c)))
        parts.append(_tbox((beam, beam, side), (x_c + hs, y, z_c)))
        if i < n_bays:  # one diagonal per bay on the top and bottom faces
            ym = y + 0.5 * (y1 - y0) / n_bays
            L = float(np.hypot(side, (y1 - y0) / n_bays))
            ang = np.arctan2((y1 - y0) / n_bays, side)
            for dz in (-hs, hs):
                d = _tbox((L, beam, beam), (0, 0, 0))
                d.apply_transform(
                    trimesh.transformations.rotation_matrix(ang * (1 if i % 2 else -1), (0, 0, 1))
                )
                d.apply_translation((x_c, ym, z_c + dz))
                parts.append(d)
    return trimesh.util.concatenate(parts)


def _transform_part(part: Part, R: np.ndarray, p: np.ndarray, part_id: int | None = None) -> Part:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = p
    return Part(
        part.mesh.copy().apply_transform(T),
        part.rgb,
        part.specular,
        part.part_id if part_id is None else part_id,
        part.name,
    )


def fixture_at_port(port: Port, is_target: bool = True) -> list[Part]:
    parts = berthing_fixture()
    out = [
        _transform_part(pt, port.R_lvlh_t, port.p_lvlh_t, None if is_target else ID_OTHER_FIXTURE)
        for pt in parts
    ]
    return out


def station(target_port: int) -> list[Part]:
    """ISS-like structure in LVLH with fixtures on all six ports; the target port's fixture
    keeps its part ids, the others are labelled ID_OTHER_FIXTURE."""
    white = (0.86, 0.86, 0.84)
    parts: list[Part] = []
    for _, x0, x1, r in MODULES_ALONG_X:
        parts.append(Part(_cyl_x(x0, x1, r), white, 0.25, ID_MODULE))
    # Two laboratory modules on the sides of the forward node.
    parts.append(Part(_cyl_y(2.2, 9.0, 2.1, x=15.0), white, 0.25, ID_MODULE))
    parts.append(Part(_cyl_y(-9.0, -2.2, 2.1, x=15.0), white, 0.25, ID_MODULE))
    # Integrated truss above the lab, with its mast.
    truss_x, truss_z = 7.0, -5.6
    parts.append(Part(_truss(truss_x, truss_z, -40.0, 40.0), (0.62, 0.62, 0.60), 0.3, ID_TRUSS))
    parts.append(Part(_tbox((1.2, 1.2, 2.2), (truss_x, 0.0, -3.0)), (0.62, 0.62, 0.60), 0.3, ID_TRUSS))
    # Radiators hanging aft of the truss, panels in the X-Y plane.
    for sy in (-1, 1):
        for k in range(3):
            y = sy * (11.0 + 4.0 * k)
            parts.append(
                Part(
                    _tbox((13.0, 3.2, 0.08), (truss_x - 8.0, y, truss_z + 0.3 * k)),
                    (0.93, 0.93, 0.93),
                    0.15,
                    ID_RADIATOR,
                )
            )
    # Solar array wings at the truss ends, extending along +-X.
    for sy in (-1, 1):
        for y in (sy * 31.0, sy * 37.0):
            for sx in (-1, 1):
                xc = truss_x + sx * (1.5 + 17.0)
                parts.append(
                    Part(_tbox((33.0, 4.6, 0.05), (xc, y, truss_z)), (0.12, 0.16, 0.38), 0.9, ID_SOLAR_ARRAY)
                )
            parts.append(Part(_tbox((0.3, 0.3, 0.3), (truss_x, y, truss_z)), (0.5, 0.5, 0.5), 0.2, ID_TRUSS))
    # Adapters and fixtures on the six ports.
    for number, port in PORTS.items():
        # The adapter leaves the drogue's room free: a solid one had its front face 5 cm behind
        # the plate, across the funnel, hiding its bottom and the throat keypoint (0.18 m).
        a = _to_trimesh(
            _frustum(
                0.30, 0.30, FIXTURE.rim_depth_m + FIXTURE.plate_thickness_m - 0.001, ADAPTER_LENGTH_M + 0.3
            )
            - drogue_envelope()
        )
        collar = _to_trimesh(_frustum(0.55, 0.55, ADAPTER_LENGTH_M - 0.15, ADAPTER_LENGTH_M + 0.3))
        for m in (a, collar):
            parts.append(
                _transform_part(Part(m, (0.80, 0.80, 0.78), 0.3, ID_ADAPTER), port.R_lvlh_t, port.p_lvlh_t)
            )
        parts.extend(fixture_at_port(port, is_target=(number == target_port)))
    return parts


def scene_parts(background: str, target_port: int) -> list[Part]:
    """`iss`: whole station; `perlin`: only the target port's berthing fixture."""
    if background == "iss":
        return station(target_port)
    if background == "perlin":
        return fixture_at_port(PORTS[target_port], is_target=True)
    raise ValueError(f"unknown background {background!r} (iss|perlin)")


def triangle_count(parts: list[Part]) -> int:
    return int(sum(len(p.mesh.faces) for p in parts))
