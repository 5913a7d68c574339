"""Foxglove's well-known messages of the flight log, which the app draws as they are: the
fixture's outline (SceneUpdate), poses, transforms and raw images. ``fm`` is the SDK's
``foxglove.messages`` module, imported by the caller (the SDK is loaded only when a log is)."""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

import numpy as np

from oibar.nav.flightlog.channels import FRAME_CAMERA
from oibar.nav.flightlog.messages import vec


def fixture_outline_entities(fm: Any, frames: Iterable[tuple[str, tuple[float, float, float, float]]]) -> Any:
    """A SceneUpdate with the fixture's outline (rim, drogue mouth, pin guides, connector) in
    each of ``frames`` (frame id, RGBA colour): in the image it lies over the fixture when the
    pose is right."""
    from oibar.geometry.fixture import FIXTURE, fixture_corners_t

    d = FIXTURE

    def loop(points: np.ndarray) -> list[Any]:
        return [fm.Point3(x=float(p[0]), y=float(p[1]), z=float(p[2])) for p in (*points, points[0])]

    def circle(cx: float, cy: float, r: float, n: int = 24) -> np.ndarray:
        a = np.linspace(0.0, 2 * np.pi, n, endpoint=False)
        return np.stack([cx + r * np.cos(a), cy + r * np.sin(a), np.zeros(n)], axis=1)

    cx, cy = d.connector_xy_m
    cw, ch = d.connector_size_m[0] / 2, d.connector_size_m[1] / 2
    shapes = [
        fixture_corners_t(d),
        circle(0.0, 0.0, d.drogue_mouth_radius_m),
        circle(-d.pin_guide_x_m, 0.0, d.pin_guide_radius_m),
        circle(d.pin_guide_x_m, 0.0, d.pin_guide_radius_m),
        np.array(
            [[cx - cw, cy - ch, 0], [cx + cw, cy - ch, 0], [cx + cw, cy + ch, 0], [cx - cw, cy + ch, 0]]
        ),
    ]
    entities = []
    for frame_id, rgba in frames:
        colour = fm.Color(r=rgba[0], g=rgba[1], b=rgba[2], a=rgba[3])
        lines = [
            fm.LinePrimitive(
                type=fm.LinePrimitiveLineType.LineStrip,
                thickness=2.0,
                scale_invariant=True,
                points=loop(s),
                color=colour,
            )
            for s in shapes
        ]
        entities.append(
            fm.SceneEntity(frame_id=frame_id, id=f"outline_{frame_id}", frame_locked=True, lines=lines)
        )
    return fm.SceneUpdate(entities=entities)


def stamp(fm: Any, log_time_ns: int) -> Any:
    """A Foxglove Timestamp of a log time (wall clock, ns)."""
    return fm.Timestamp(log_time_ns // 1_000_000_000, log_time_ns % 1_000_000_000)


def pose(fm: Any, T_m: Any, q_wxyz: Any) -> Any:
    t, q = vec(T_m, 3), vec(q_wxyz, 4)
    return fm.Pose(
        position=fm.Vector3(x=t[0], y=t[1], z=t[2]),
        orientation=fm.Quaternion(x=q[1], y=q[2], z=q[3], w=q[0]),
    )


def transform(fm: Any, when: Any, child: str, T_m: Any, q_wxyz: Any) -> bytes:
    """The encoded FrameTransform camera -> ``child`` at ``when`` (a Timestamp)."""
    t, q = vec(T_m, 3), vec(q_wxyz, 4)
    msg = fm.FrameTransform(
        timestamp=when,
        parent_frame_id=FRAME_CAMERA,
        child_frame_id=child,
        translation=fm.Vector3(x=t[0], y=t[1], z=t[2]),
        rotation=fm.Quaternion(x=q[1], y=q[2], z=q[3], w=q[0]),
    )
    data: bytes = msg.encode()
    return data


def raw_image(fm: Any, image: np.ndarray, log_time_ns: int) -> bytes:
    """The encoded RawImage (rgb8, the navigator's own pixels) of a frame."""
    img = np.ascontiguousarray(image)
    h, w = img.shape[:2]
    msg = fm.RawImage(
        timestamp=stamp(fm, log_time_ns),
        frame_id=FRAME_CAMERA,
        width=int(w),
        height=int(h),
        encoding="rgb8",
        step=int(w) * 3,
        data=img.tobytes(),
    )
    data: bytes = msg.encode()
    return data
