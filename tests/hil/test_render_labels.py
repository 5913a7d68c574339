"""Label consistency: what the renderer draws lands where the camera model projects the pose."""

import numpy as np
import pytest
import trimesh

from oibar.geometry.camera import PinholeCamera
from oibar.geometry.fixture import FIXTURE, fixture_corners_t
from oibar.geometry.rotations import rotvec_to_matrix
from oibar.geometry.transforms import transform_points
from oibar_hil.meshes import ID_BOUNDARY, Part, fixture_at_port
from oibar_hil.ports import PORTS

CAM = PinholeCamera()
PORT = PORTS[1]
MARKER_POINTS_T = np.vstack([[0.0, 0.0, 0.0], fixture_corners_t() * 0.8])
MARKER_IDS = [101, 102, 103, 104, 105]

# (rotvec F_t -> cam, T_cam_target): aligned, off-axis, misaligned, rolled, close.
POSES = [
    (np.zeros(3), np.array([0.0, 0.12, 2.3])),
    (np.zeros(3), np.array([-0.9, 0.4, 6.0])),
    (np.radians([6.0, -8.0, 0.0]), np.array([0.15, -0.05, 1.5])),
    (np.radians([3.0, 2.0, 35.0]), np.array([0.05, 0.1, 3.0])),
    (np.radians([0.0, 4.0, -10.0]), np.array([0.0, 0.12, 0.9])),
]


def _markers(size_m: float) -> list[Part]:
    """Thin squares (front face on the berthing plane) at the origin and near the corners."""
    parts = []
    for pid, p in zip(MARKER_IDS, MARKER_POINTS_T, strict=True):
        m = trimesh.creation.box(extents=(size_m, size_m, 0.002))
        m.apply_translation(p + [0, 0, 0.001])
        m.apply_transform(
            np.block([[PORT.R_lvlh_t, PORT.p_lvlh_t[:, None]], [np.zeros((1, 3)), np.ones((1, 1))]])
        )
        parts.append(Part(m, (1, 1, 1), 0.0, pid))
    return parts


def _camera_in_lvlh(R_cam_t, T_cam_t):
    R_t_cam = R_cam_t.T
    p_t_cam = -R_t_cam @ T_cam_t
    return PORT.R_lvlh_t @ R_t_cam, PORT.p_lvlh_t + PORT.R_lvlh_t @ p_t_cam


def _render_ids(renderer, parts, rotvec, T):
    renderer.load_scene(parts, "perlin", PORT.p_lvlh_t, perlin_seed=0)
    R_cam_t = rotvec_to_matrix(rotvec)
    R_l_c, p_l_c = _camera_in_lvlh(R_cam_t, T)
    ids = renderer.render(R_l_c, p_l_c, np.array([1.0, 0.0, -1.0]), mode="id")[:, :, 0]
    return ids, R_cam_t


@pytest.mark.parametrize("pose", range(len(POSES)))
def test_marker_centroids_match_projection(gl_renderer, pose):
    rotvec, T = POSES[pose]
    # ~12 px markers whatever the range, so pixel quantisation stays well below the tolerance.
    ids, R_cam_t = _render_ids(gl_renderer, _markers(0.02 * T[2]), rotvec, T)
    expected = CAM.project(transform_points(MARKER_POINTS_T, R_cam_t, T))
    for pid, uv in zip(MARKER_IDS, expected, strict=True):
        rows, cols = np.nonzero(ids == pid)
        assert len(rows) > 4, f"marker {pid} not drawn"
        # Pixel (col, row) has its centre at (col + 0.5, row + 0.5) in our convention.
        centroid = np.array([cols.mean() + 0.5, rows.mean() + 0.5])
        assert np.linalg.norm(centroid - uv) < 0.5, (pid, centroid, uv)


@pytest.mark.parametrize("pose", [0, 2, 3])
def test_fixture_rectangle_corners_match_projection(gl_renderer, pose):
    rotvec, T = POSES[pose]
    ids, R_cam_t = _render_ids(gl_renderer, fixture_at_port(PORT), rotvec, T)
    corners = CAM.project(transform_points(fixture_corners_t(), R_cam_t, T))
    rows, cols = np.nonzero(ids == ID_BOUNDARY)
    centres = np.stack([cols + 0.5, rows + 0.5], axis=1)
    # Every rim pixel lies inside the projected outer rectangle (to within a pixel) ...
    edges = np.roll(corners, -1, axis=0) - corners
    rel = centres[:, None, :] - corners[None]
    # Signed distance to each edge line, positive on the polygon's inner side.
    cross = edges[None, :, 0] * rel[:, :, 1] - edges[None, :, 1] * rel[:, :, 0]
    area2 = np.sum(corners[:, 0] * np.roll(corners[:, 1], -1) - np.roll(corners[:, 0], -1) * corners[:, 1])
    inner = np.sign(area2) * cross / np.linalg.norm(edges, axis=1)[None]
    outward = -inner
    assert outward.max() <= 1.0
    # ... and each projected corner touches the drawn rim: a covered pixel centre must lie inside
    # the polygon, so near a (possibly rotated, foreshortened) corner the nearest one can be a
    # little more than a pixel diagonal away. The sub-pixel check is the marker test above.
    for c in corners:
        assert np.min(np.linalg.norm(centres - c, axis=1)) <= 2.0


def test_shaded_frame_shows_fixture_over_background(gl_renderer):
    parts = fixture_at_port(PORT)
    gl_renderer.load_scene(parts, "perlin", PORT.p_lvlh_t, perlin_seed=3)
    R_l_c, p_l_c = _camera_in_lvlh(np.eye(3), np.array([0.0, 0.12, 2.0]))
    img = gl_renderer.render(R_l_c, p_l_c, np.array([0.6, 0.0, -0.8]))
    assert img.shape == (480, 744, 3) and img.dtype == np.uint8
    assert img.std() > 10  # Perlin backdrop is not flat
    u, v = CAM.project(np.array([[0.0, 0.12 - 0.14, 2.0]]))[0]  # on the plate, above the drogue
    assert img[int(v), int(u)].mean() > 40  # the sunlit plate is visible
    assert FIXTURE.width_m > FIXTURE.height_m
