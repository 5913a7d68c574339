"""Mitsuba 3 as the second renderer: registered with ours (the same pixels belong to the same
parts, up to edge pixels) and on the same radiometric scale (a Lambertian plate under the Sun
comes out as ours draws it)."""

import numpy as np
import pytest
import trimesh

from oibar.geometry.camera import PinholeCamera
from oibar_hil.meshes import ID_ADAPTER, Part, scene_parts
from oibar_hil.ports import PORTS
from oibar_hil.render_mitsuba import MitsubaRenderer, MitsubaSettings, env_directions
from oibar_hil.rig.camera import OrbitClock, pose_to_lvlh, scene_spec

CAM = PinholeCamera()


def test_the_environment_map_directions_are_mitsubas():
    """Pixel centres of the lat-long map: +y at the top row, -z at u = 0 and +x a quarter on."""
    d = env_directions(8)
    assert d.shape == (4, 8, 3) and np.allclose(np.linalg.norm(d, axis=-1), 1.0)
    assert d[0, 0, 1] > 0.9 and d[-1, 0, 1] < -0.9  # top row looks up (+y), bottom row down
    mid = d[1:3].mean(axis=0)  # the equator's two rows: y cancels
    assert np.argmax(-mid[:, 2]) in (0, 7)  # -z at u = 0 (wrapping)
    assert np.argmax(mid[:, 0]) in (1, 2)  # +x a quarter turn on


def test_its_silhouettes_are_ours_up_to_edge_pixels(gl_renderer):
    """Same meshes, same camera, same pose: every pixel names the same part in both renderers
    but where a part's edge crosses it (the rasteriser and the ray caster may round it either
    way). A flipped axis, a principal point off by a pixel or a wrong field of view fails this."""
    spec = scene_spec("seq01")
    port = PORTS[spec.port]
    parts = scene_parts(spec.background, spec.port)
    R, p, _, _ = pose_to_lvlh(np.array([0.05, -0.03, 1.2]), np.array([0.03, -0.02, 0.05]), port)
    gl_renderer.load_scene(parts, spec.background, port.p_lvlh_t, perlin_seed=spec.seed)
    ours = gl_renderer.render(R, p, np.array([0.0, 0.0, -1.0]), mode="id")[..., 0]
    mi = MitsubaRenderer(mitsuba=MitsubaSettings(spp=1))
    mi.load_scene(parts, spec.background, port.p_lvlh_t, perlin_seed=spec.seed)
    theirs = mi.render(R, p, np.array([0.0, 0.0, -1.0]), mode="id")[..., 0]
    fixture = (ours > 0) & (ours < ID_ADAPTER)
    assert fixture.sum() > 15_000  # the fixture fills a good part of the frame at 1.2 m
    differ = ours != theirs
    assert differ.mean() < 0.005, differ.mean()
    # every pixel that differs lies on an edge: a neighbour carries the other renderer's label
    pad = np.pad(ours, 1, mode="edge")
    near = np.zeros_like(differ)
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            near |= pad[1 + dy : 1 + dy + ours.shape[0], 1 + dx : 1 + dx + ours.shape[1]] == theirs
    assert np.all(near[differ])


def test_a_lambertian_plate_under_the_sun_comes_out_as_ours(gl_renderer):
    """The units: our shading is albedo x irradiance with the Sun's at 1; Mitsuba's radiance is
    albedo x E / pi, so its Sun has irradiance pi. With the Earth below at night (no Earth-shine)
    the only difference left is our 3 % ambient."""
    port = PORTS[1]
    plate = trimesh.creation.box(extents=(2.0, 2.0, 0.02))
    M = np.eye(4)
    M[:3, :3], M[:3, 3] = port.R_lvlh_t, port.p_lvlh_t + port.R_lvlh_t @ [0.0, 0.0, 0.01]
    plate.apply_transform(M)  # its front face on the berthing plane, facing -z of F_t
    parts = [Part(plate, (0.5, 0.5, 0.5), 0.0, 2)]
    R_l_c, p_l_c = port.R_lvlh_t, port.p_lvlh_t + port.R_lvlh_t @ [0.0, 0.0, -1.5]
    sun_t = np.array([0.0, 0.6, -0.8])  # 37 deg off the plate's normal
    sun = port.R_lvlh_t @ sun_t
    earth_c = np.array([0.0, 0.0, 6371.0 + 420.0])
    night = sun @ earth_c > 0  # the Sun beyond the Earth: its face towards us is dark
    if not night:
        earth_c = -earth_c  # put the Earth on the Sun's side, so we see its night
    gl_renderer.load_scene(parts, "perlin", port.p_lvlh_t, perlin_seed=0)
    ours = gl_renderer.render(R_l_c, p_l_c, sun, earth_center_lvlh_km=earth_c).astype(float)
    mi = MitsubaRenderer(mitsuba=MitsubaSettings(spp=16))
    mi.load_scene(parts, "perlin", port.p_lvlh_t, perlin_seed=0)
    theirs = mi.render(R_l_c, p_l_c, sun, earth_center_lvlh_km=earth_c).astype(float)
    box = (slice(200, 280), slice(330, 410))  # the plate's middle
    want = 255 * (0.5 * 0.8) ** (1 / 2.2)  # albedo x cos, gamma-encoded: no ambient
    assert theirs[box].mean() == pytest.approx(want, abs=3.0)
    assert ours[box].mean() == pytest.approx(255 * (0.5 * (0.8 + 0.03)) ** (1 / 2.2), abs=2.0)


def test_the_orbit_clock_gives_mitsuba_what_it_gives_ours():
    """The frames of a look are rendered for the rig's Sun and Earth (OrbitClock): the renderer
    takes them as ours does, and refuses a frame before a scene is loaded."""
    clock = OrbitClock(scene_spec("seq01"))
    sun, R_ecef = clock.at(0.0)
    mi = MitsubaRenderer(mitsuba=MitsubaSettings(spp=1))
    with pytest.raises(RuntimeError, match="load_scene"):
        mi.render(np.eye(3), np.zeros(3), sun, R_ecef, clock.earth_center_lvlh_km)
