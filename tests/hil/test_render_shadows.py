"""Shadows from both cascades of the shadow-map atlas land where the Sun's geometry puts them,
and a shaded frame does not depend on what was rendered before it (GL state, shadow cache)."""

import numpy as np
import trimesh

from oibar.geometry.camera import PinholeCamera
from oibar.geometry.transforms import transform_points
from oibar_hil.meshes import Part
from oibar_hil.ports import PORTS

CAM = PinholeCamera()
PORT = PORTS[1]
T_CAM = np.array([0.0, 0.12, 12.0])  # aligned camera 12 m in front of the berthing plane
SUN_T = np.array([0.3, 0.2, -1.0]) / np.linalg.norm([0.3, 0.2, -1.0])  # towards the camera side
# (blocker centre in F_t, cube edge): one inside the near cascade (+-0.6 m), one only in the far one.
BLOCKERS = [(np.array([0.0, 0.0, -1.0]), 0.2), (np.array([4.0, 2.5, -1.5]), 0.6)]


def _to_lvlh(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    mesh.apply_transform(
        np.block([[PORT.R_lvlh_t, PORT.p_lvlh_t[:, None]], [np.zeros((1, 3)), np.ones((1, 1))]])
    )
    return mesh


def _scene() -> list[Part]:
    slab = trimesh.creation.box(extents=(30.0, 30.0, 0.1))
    slab.apply_translation([0.0, 0.0, 0.05])  # front face on the berthing plane z = 0
    parts = [Part(_to_lvlh(slab), (0.8, 0.8, 0.8), 0.0, 2)]
    for centre, edge in BLOCKERS:
        b = trimesh.creation.box(extents=(edge, edge, edge))
        b.apply_translation(centre)
        parts.append(Part(_to_lvlh(b), (0.8, 0.8, 0.8), 0.0, 3))
    return parts


def _camera_pose():
    R_t_cam = np.eye(3)
    return PORT.R_lvlh_t @ R_t_cam, PORT.p_lvlh_t + PORT.R_lvlh_t @ (-R_t_cam @ T_CAM)


def _pixel(p_t: np.ndarray) -> tuple[int, int]:
    u, v = CAM.project(transform_points(p_t[None], np.eye(3), T_CAM))[0]
    return int(v), int(u)


def test_shadows_from_near_and_far_cascades(gl_renderer):
    gl_renderer.load_scene(_scene(), "perlin", PORT.p_lvlh_t, perlin_seed=0)
    R_l_c, p_l_c = _camera_pose()
    img = gl_renderer.render(R_l_c, p_l_c, PORT.R_lvlh_t @ SUN_T).astype(float).mean(axis=2)
    for centre, edge in BLOCKERS:
        shadow = centre - SUN_T * (centre[2] / SUN_T[2])  # blocker centre cast on z = 0
        lit = shadow + np.array([0.0, -3.0 * edge, 0.0])  # beside the shadow, in the Sun
        assert img[_pixel(shadow)] < 0.4 * img[_pixel(lit)], (centre, img[_pixel(shadow)], img[_pixel(lit)])
    # Far from both blockers the slab is evenly lit.
    assert abs(img[_pixel(np.array([-3.0, 1.0, 0.0]))] - img[_pixel(np.array([-2.0, 1.5, 0.0]))]) <= 2


def test_shaded_frame_independent_of_history(gl_renderer):
    gl_renderer.load_scene(_scene(), "perlin", PORT.p_lvlh_t, perlin_seed=0)
    R_l_c, p_l_c = _camera_pose()
    sun_a = PORT.R_lvlh_t @ SUN_T
    sun_b = PORT.R_lvlh_t @ (np.array([-0.2, 0.1, -1.0]) / np.linalg.norm([-0.2, 0.1, -1.0]))
    first = gl_renderer.render(R_l_c, p_l_c, sun_a)
    gl_renderer.render(R_l_c, p_l_c, sun_a, mode="id")  # leaves other GL state behind
    gl_renderer.render(R_l_c, p_l_c, sun_b)  # re-renders the shadow maps
    again = gl_renderer.render(R_l_c, p_l_c, sun_a)  # ... and back
    assert np.array_equal(first, again)
