"""Shadows from both cascades of the shadow-map atlas land where the Sun's geometry puts them,
and a shaded frame does not depend on what was rendered before it (GL state, shadow cache)."""

import numpy as np
import pytest
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


def test_an_occluder_of_one_centimetre_casts_its_shadow(gl_renderer):
    """A 1 cm step (the rim is 2 cm, the pin-guide bosses less) shades the plate beside it: the
    depth bias is about a texel scaled with the slope, not a constant ~12 cm of the shadow depth
    range that hid every occluder closer than that along the light."""
    slab = trimesh.creation.box(extents=(2.0, 2.0, 0.1))
    slab.apply_translation([0.0, 0.0, 0.05])  # front face on z = 0
    step = trimesh.creation.box(extents=(0.06, 0.06, 0.01))
    step.apply_translation([0.0, 0.0, -0.005])  # 1 cm proud of the plate, towards the camera
    parts = [Part(_to_lvlh(slab), (0.8, 0.8, 0.8), 0.0, 2), Part(_to_lvlh(step), (0.8, 0.8, 0.8), 0.0, 3)]
    gl_renderer.load_scene(parts, "perlin", PORT.p_lvlh_t, perlin_seed=0)
    R_t_cam = np.eye(3)
    T_cam = np.array([0.0, 0.0, 0.8])
    R_l_c, p_l_c = PORT.R_lvlh_t @ R_t_cam, PORT.p_lvlh_t + PORT.R_lvlh_t @ (-R_t_cam @ T_cam)
    sun_t = np.array([np.cos(np.radians(30.0)), 0.0, -np.sin(np.radians(30.0))])  # 30 deg above the plate
    img = gl_renderer.render(R_l_c, p_l_c, PORT.R_lvlh_t @ sun_t).astype(float).mean(axis=2)

    def pixel(p_t):
        u, v = CAM.project(transform_points(np.asarray(p_t, float)[None], np.eye(3), T_cam))[0]
        return int(v), int(u)

    # the shadow falls away from the Sun (-x), 1 cm / tan 30 deg = 17 mm long behind the step's edge
    shadow = pixel([-0.03 - 0.008, 0.0, 0.0])
    lit = pixel([-0.03 - 0.008, 0.08, 0.0])  # the same distance from the step, beside its shadow
    assert img[shadow] < 0.6 * img[lit], (img[shadow], img[lit])
    # and no acne: the open plate is evenly lit
    a, b = img[pixel([0.15, 0.1, 0.0])], img[pixel([0.25, -0.15, 0.0])]
    assert abs(a - b) <= 2, (a, b)


def _look_at(eye: np.ndarray, target: np.ndarray) -> np.ndarray:
    """R_lvlh_cam of a camera (OpenCV axes) at `eye` looking at `target`."""
    z = (target - eye) / np.linalg.norm(target - eye)
    x = np.cross(z, np.array([0.0, 1.0, 0.0]))
    x /= np.linalg.norm(x)
    return np.stack([x, np.cross(z, x), z], axis=1)


def test_earth_shine_comes_from_the_whole_disc_and_a_wall_shades_it(gl_renderer):
    """The Earth spans ~139 deg from LEO: a plate facing it is lit by the whole disc, and a wall
    hanging beside a point hides about half of that disc from it, so the plate is darker next to
    the wall than away from it (a directional fill light without shadow lit both alike). The Sun
    stands overhead: the plate's Earth-facing side gets no direct Sun, and the Earth below is day."""
    f = PORT.p_lvlh_t
    plate = trimesh.creation.box(extents=(2.0, 2.0, 0.02))
    plate.apply_translation(f)  # its underside (normal +Z, towards the Earth) 1 cm below the focus
    wall = trimesh.creation.box(extents=(0.02, 2.0, 0.5))
    wall.apply_translation(f + np.array([0.0, 0.0, 0.26]))  # hangs below the plate at x = 0
    parts = [Part(plate, (0.8, 0.8, 0.8), 0.0, 2), Part(wall, (0.8, 0.8, 0.8), 0.0, 3)]
    gl_renderer.load_scene(parts, "perlin", f, perlin_seed=0)
    eye, target = f + np.array([1.4, 0.0, 1.0]), f + np.array([0.5, 0.0, 0.01])
    R_l_c = _look_at(eye, target)
    img = gl_renderer.render(R_l_c, eye, np.array([0.0, 0.0, -1.0])).astype(float).mean(axis=2)

    def pixel(p):
        u, v = CAM.project(transform_points(np.asarray(p, float)[None], R_l_c.T, -R_l_c.T @ eye))[0]
        return int(v), int(u)

    near, away = img[pixel(f + [0.04, 0.3, 0.011])], img[pixel(f + [0.9, 0.3, 0.011])]
    assert near < 0.85 * away, (near, away)
    assert away > 100  # lit by the day side of the Earth alone: far above the ambient term


def test_earth_shine_follows_the_sunlit_part_of_the_disc():
    """A Lambertian Earth: below a station with the Sun overhead the whole disc is day, and a
    surface facing it gets the integral of albedo / pi x cos(Sun on the ground) x cos(incidence)
    over the disc (here by quadrature on a fine polar grid; the six patches within 10 %); with the
    Sun behind the Earth, night (no Earth-shine)."""
    from oibar_hil.render import EARTH_RADIUS_KM, EarthLight

    c = np.array([0.0, 0.0, 6371.0 + 420.0])
    earth = EarthLight(c, 6, ground=np.full((2, 4, 3), 0.3))  # a uniformly grey Earth
    sin2 = (EARTH_RADIUS_KM / np.linalg.norm(c)) ** 2
    facing = np.array([0.0, 0.0, 1.0])  # a surface facing nadir sees each patch at this cosine

    def irradiance(sun):
        rgb = earth.weights(sun).T @ np.maximum(earth.dirs @ facing, 0.0)
        assert rgb == pytest.approx(np.full(3, rgb[0]))  # grey
        return float(rgb[0])

    day, night = irradiance(np.array([0.0, 0.0, -1.0])), irradiance(np.array([0.0, 0.0, 1.0]))
    # the Sun 60 deg from the zenith: the ground the station sees is tilted at most ~20 deg, so
    # it is lit at about cos 60 deg
    dusk = irradiance(np.array([np.sin(np.radians(60.0)), 0.0, -np.cos(np.radians(60.0))]))
    # quadrature: rays at angle t from nadir meet the ground where its normal is tilted by
    # t + (angle at the Earth's centre); the Sun overhead lights it at that tilt's cosine
    alpha = np.arcsin(np.sqrt(sin2))
    t = (np.arange(2000) + 0.5) / 2000 * alpha
    clen = np.linalg.norm(c)
    ground = np.arcsin(np.clip(clen / EARTH_RADIUS_KM * np.sin(t), -1, 1))  # angle of incidence on the ground
    tilt = ground - t  # the ground normal's angle from the station's zenith
    integrand = 0.3 / np.pi * np.cos(tilt) * np.cos(t) * 2 * np.pi * np.sin(t)
    exact = float(np.sum(integrand) * alpha / 2000)
    assert exact < 0.3 * sin2  # below a uniformly bright disc's albedo x sin^2
    assert day == pytest.approx(exact, rel=0.10)
    assert night == 0.0
    assert 0.4 * day < dusk < 0.6 * day


@pytest.mark.parametrize("seed", [0, 2, 3])
def test_earth_shine_takes_the_colour_of_the_ground_as_mitsubas_environment_does(seed):
    """Earth-shine is the Earth's texture (ground and clouds) under the sunlit disc, not a grey
    constant: the irradiance it gives a nadir-facing surface, per colour channel, is what the
    path tracer's environment map (render_mitsuba.earth_radiance_map, the same texture) gives it
    by quadrature over its pixels: within 3 % from the fine directions, within 15 % from the
    six shadow-mapped patches (their centres' cosine stands for the patch's: +7 % on a uniform
    Earth, up to +13 % in one channel here). Three places over the globe, of different colour and
    brightness (0.13-0.71 of the Sun's irradiance)."""
    from scipy.spatial.transform import Rotation

    from oibar_hil.render import (
        DEFAULT_EARTH_CENTER_LVLH_KM,
        EARTH_FINE_SAMPLES,
        EarthLight,
        earth_rgba,
        fibonacci_disc,
    )
    from oibar_hil.render_mitsuba import earth_radiance_map, env_directions

    c = np.array(DEFAULT_EARTH_CENTER_LVLH_KM)
    R_ecef_lvlh = Rotation.random(random_state=seed).as_matrix()
    sun = np.array([0.3, 0.2, -1.0]) / np.linalg.norm([0.3, 0.2, -1.0])
    facing = np.array([0.0, 0.0, 1.0])
    width = 1024
    d = env_directions(width)
    L = earth_radiance_map(d, c, R_ecef_lvlh, sun, earth_rgba())  # on the Sun = pi scale
    theta = (np.arange(width // 2) + 0.5) / (width // 2) * np.pi
    d_omega = (np.pi / (width // 2)) * (2 * np.pi / width) * np.sin(theta)[:, None]
    mitsuba = (L * (np.maximum(d @ facing, 0.0) * d_omega)[..., None]).reshape(-1, 3).sum(0) / np.pi

    earth = EarthLight(c, 6)
    fine_dirs = fibonacci_disc(c, EARTH_FINE_SAMPLES)
    fine = (
        earth.radiance(sun, R_ecef_lvlh) * (np.maximum(fine_dirs @ facing, 0.0) * earth.d_omega)[:, None]
    ).sum(0)
    patches = earth.weights(sun, R_ecef_lvlh).T @ np.maximum(earth.dirs @ facing, 0.0)
    assert fine == pytest.approx(mitsuba, rel=0.03)
    assert patches == pytest.approx(mitsuba, rel=0.15)
    # the colour too (a grey Earth of albedo 0.3 gives 0.25 in every channel at every place)
    assert fine / fine.mean() == pytest.approx(mitsuba / mitsuba.mean(), abs=0.03)
