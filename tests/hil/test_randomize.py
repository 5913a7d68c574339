"""The randomised look (issue 58, part 3): draws are the seed's and within the documented bounds;
a spec without it renders as before; a randomised frame differs from the default one but keeps
the fixture's silhouette; lamps light by the inverse square and cast their own shadows; the
optics move the corner as drawn and leave the centre."""

from __future__ import annotations

import importlib.util
import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import trimesh

from oibar.geometry.camera import PinholeCamera
from oibar_hil import randomize as rz
from oibar_hil.dataset import SequenceSpec, generate_dataset, plan_sequence, spec_dict
from oibar_hil.meshes import ID_BOUNDARY, ID_CONNECTOR, Part, scene_parts
from oibar_hil.ports import PORTS

REPO = Path(__file__).resolve().parents[2]
CAM = PinholeCamera()
D = rz.DEFAULT


def _within(x: float, lo_hi: tuple[float, float], tol: float = 1e-3) -> bool:
    return lo_hi[0] - tol <= x <= lo_hi[1] + tol


# ----------------------------------------------------------------------------- draws
def test_a_look_seed_names_one_look():
    assert rz.look_for(123) == rz.look_for(123)
    assert rz.look_for(123) != rz.look_for(124)
    # its own stream: not the numbers numpy.random.default_rng(seed) gives the trajectory
    assert rz.look_for(7) != rz.draw(np.random.default_rng(7))


MATERIAL_BOUNDS = {  # kind: (specular, shininess)
    "painted": ((0.05, 0.4), (8, 64)),
    "print_grey": ((0.0, 0.06), (4, 16)),
    "aluminium_bare": ((0.5, 0.9), (40, 250)),
    "aluminium_anodised": ((0.2, 0.5), (24, 96)),
    "mli": ((0.6, 1.0), (80, 400)),
}


def test_draws_stay_within_the_documented_bounds():
    looks = [rz.look_for(s) for s in range(1500)]
    kinds, lightings, backdrops = [], [], []
    for lk in looks:
        assert [name for name, _ in lk.materials] == list(rz.FIXTURE_PARTS)
        if lk.scheme == "uniform":
            assert len({m for _, m in lk.materials}) == 1
        for _, m in lk.materials:
            kinds.append(m.kind)
            if m.kind in MATERIAL_BOUNDS:
                spec, shin = MATERIAL_BOUNDS[m.kind]
                assert _within(m.specular, spec) and _within(m.shininess, shin, 0.1), m
                assert all(0.0 <= c <= 1.0 for c in m.rgb), m
            if m.kind == "print_grey":
                assert max(m.rgb) - min(m.rgb) <= 0.04 + 1e-3 and _within(min(m.rgb), (0.40, 0.70))
                assert _within(m.banding, (0.02, 0.08)) and _within(m.band_period_m, (0.001, 0.004), 1e-5)
            if m.kind == "aluminium_bare":
                assert _within(m.stretch, (10.0, 40.0), 0.1)
            if m.kind == "mli":
                assert _within(m.bump, (0.15, 0.5)) and _within(m.scale_per_m, (15.0, 50.0), 0.01)
            else:
                assert m.bump == 0.0 and _within(m.scale_per_m, (8.0, 60.0), 0.01)
        lightings.append(lk.lighting)
        backdrops.append(lk.backdrop)
        assert (
            len(lk.lamps) == {"lamp_at_camera": 1, "lamp_off_camera": 1}.get(lk.lighting, len(lk.lamps))
            and len(lk.lamps) <= rz.MAX_LAMPS
        )
        assert (len(lk.lamps) > 0) == lk.lighting.startswith("lamp")
        assert (lk.sun_scale > 0) == (lk.lighting in ("sun", "sun_earth"))
        assert (lk.earth_scale > 0) == (lk.lighting in ("earth", "sun_earth"))
        if lk.sun_scale:
            assert _within(lk.sun_scale, D.sun_scale)
        if lk.lighting == "earth":
            assert _within(lk.earth_scale, D.earth_alone_scale)
        for lamp in lk.lamps:
            assert _within(lamp.irradiance, D.lamp_irradiance) and _within(
                lamp.cone_deg, D.lamp_cone_deg, 0.01
            )
            assert lamp.cone_deg * 0.2 - 0.01 <= lamp.soft_deg <= lamp.cone_deg * 0.6 + 0.01
            assert max(lamp.rgb) == pytest.approx(1.0, abs=1e-3) and min(lamp.rgb) >= 0.5
            assert max(abs(a) for a in lamp.aim_m) <= D.lamp_aim_m + 1e-4
            r = float(np.hypot(*lamp.position_m[:2]))
            if lamp.mount == "camera":
                assert r <= D.lamp_at_camera_m + 1e-3 or _within(r, D.lamp_off_camera_m)
            else:
                assert lamp.mount == "world" and lamp.position_m[2] < 0  # the camera's side
                assert _within(float(np.linalg.norm(lamp.position_m)), D.lamp_world_m)
        if lk.lighting == "lamp_at_camera":
            assert lk.lamps[0].mount == "camera" and np.hypot(*lk.lamps[0].position_m[:2]) <= 0.2 + 1e-3
        assert _within(lk.ambient, D.ambient_lamps if lk.lamps else D.ambient_space)
        assert _within(lk.exposure, D.exposure)
        assert lk.vignetting == 0.0 or _within(lk.vignetting, D.vignetting)
        px = abs(rz.corner_displacement_px(lk.distortion_k1))
        assert px == 0.0 or _within(px, D.distortion_corner_px, 1e-3)
        assert lk.backdrop_gain == 1.0 or lk.backdrop in ("stars", "clutter", "perlin")
    # every value of every categorical axis is drawn, near its documented probability
    for values, names, p in (
        (kinds, rz.MATERIAL_KINDS, D.p_kind),
        (lightings, rz.LIGHTINGS, D.p_lighting),
        (backdrops, rz.BACKDROPS, D.p_backdrop),
    ):
        share = np.array([values.count(n) for n in names]) / len(values)
        assert np.all(np.abs(share - np.array(p)) < 0.05), (names, share)
    assert abs(np.mean([lk.scheme == "uniform" for lk in looks]) - D.p_uniform_scheme) < 0.05
    # the lab's look is among them: one grey print, one lamp at the camera, black
    assert any(
        lk.scheme == "uniform"
        and lk.materials[0][1].kind == "print_grey"
        and lk.lighting == "lamp_at_camera"
        and lk.backdrop == "black"
        for lk in looks
    )


# ----------------------------------------------------------------------------- specs and sets
BASE = SequenceSpec(
    name="dr",
    port=1,
    approach="+V-bar",
    sun_elevation_deg=60.0,
    background="perlin",
    seed=61,
    frame_stride=40,
)


def test_the_default_spec_keeps_its_identity_and_looks_are_checked():
    d = spec_dict(BASE)
    assert "look" not in d and "look_seed" not in d and "renderer" not in d
    lab = replace(BASE, renderer="mitsuba", look="lab")
    assert "look_seed" not in spec_dict(lab) and spec_dict(lab)["look"] == "lab"
    dr = replace(BASE, look="randomized", look_seed=9)
    assert spec_dict(dr)["look"] == "randomized" and spec_dict(dr)["look_seed"] == 9
    with pytest.raises(ValueError, match="randomized with the raster renderer"):
        replace(BASE, renderer="mitsuba", look="randomized").validate()
    with pytest.raises(ValueError):
        replace(BASE, look="lab").validate()


def test_the_randomised_training_set_is_its_own():
    """train_dr.json: every scene randomised, names and seeds of its own (none of train,
    validation or the frozen test set's 50000-50005), the size class of train.json."""
    sets = {
        n: json.loads((REPO / f"models/scenes/{n}.json").read_text())["scenes"] for n in ("train_dr", "train")
    }
    others = [
        s
        for n in ("train_sunfine", "val", "test_frozen")
        for s in json.loads((REPO / f"models/scenes/{n}.json").read_text())["scenes"]
    ]
    dr = sets["train_dr"]
    assert all(s["look"] == "randomized" for s in dr)
    assert len({s["seed"] for s in dr}) == len(dr) and len({s["name"] for s in dr}) == len(dr)
    assert not {s["seed"] for s in dr} & {s["seed"] for s in others if "seed" in s}
    assert not {s["name"] for s in dr} & {s["name"] for s in others if "name" in s}
    assert all(s["seed"] >= 60000 for s in dr)
    frames = sum(1 / s["frame_stride"] for s in dr) / sum(1 / s.get("frame_stride", 1) for s in sets["train"])
    assert 0.8 <= frames <= 1.25
    # Suns clear of validation and test scenes of the same port and background, as the others
    spec = importlib.util.spec_from_file_location("make_scenes", REPO / "models/scenes/make_scenes.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    for s in dr:
        for o in others:
            if (
                "port" in o
                and (o["port"], o["background"]) == (s["port"], s["background"])
                and o
                in [
                    *json.loads((REPO / "models/scenes/val.json").read_text())["scenes"],
                    *json.loads((REPO / "models/scenes/test_frozen.json").read_text())["scenes"],
                ]
            ):
                assert abs(o["sun_elevation_deg"] - s["sun_elevation_deg"]) >= mod.SUN_MARGIN_DEG


def test_a_randomised_sequence_records_its_look(tmp_path, gl_renderer):
    spec = replace(BASE, look="randomized", look_seed=4)
    generate_dataset(tmp_path, [spec], frames_limit=2, workers=1, progress=False)
    manifest = json.loads((tmp_path / "dr/manifest.json").read_text())
    assert manifest["config"]["look"] == json.loads(json.dumps(rz.look_for(4).as_dict()))
    ident = json.loads((tmp_path / "dr/spec.json").read_text())
    assert ident["look"] == "randomized" and ident["look_version"] == rz.LOOK_VERSION
    plain = tmp_path / "plain"
    generate_dataset(plain, [BASE], frames_limit=2, workers=1, progress=False)
    assert "look" not in json.loads((plain / "dr/manifest.json").read_text())["config"]
    assert not {"look", "look_version"} & set(json.loads((plain / "dr/spec.json").read_text()))
    a = (tmp_path / "dr/frames/000001.jpg").read_bytes()
    assert a != (plain / "dr/frames/000001.jpg").read_bytes()


# ----------------------------------------------------------------------------- rendering
def _pose(plan, range_m: float):
    k = int(np.argmin(np.abs(plan.range_m - range_m)))
    return (
        plan.R_lvlh_cam[k],
        plan.p_lvlh_cam[k],
        plan.sun_lvlh[k],
        plan.R_ecef_lvlh[k],
        plan.earth_center_lvlh_km,
    )


def _plain(**over) -> rz.LookParams:
    """A look with nothing drawn: the parts as built, the Sun alone, black, no optics."""
    base = rz.LookParams(
        seed=1, scheme="uniform", materials=(), lighting="sun", sun_scale=1.0, earth_scale=0.0,
        ambient=0.0, lamps=(), backdrop="black", backdrop_seed=0, backdrop_gain=1.0, exposure=1.0,
        vignetting=0.0, distortion_k1=0.0,
    )  # fmt: skip
    return replace(base, **over)


@pytest.fixture(scope="module")
def fixture_view():
    plan = plan_sequence(BASE)
    return scene_parts("perlin", 1), PORTS[1], _pose(plan, 1.2)


def test_the_default_look_comes_back_unchanged_after_a_randomised_one(gl_renderer, fixture_view):
    parts, port, pose = fixture_view
    gl_renderer.load_scene(parts, "perlin", port.p_lvlh_t, perlin_seed=61)
    before = gl_renderer.render(*pose)
    gl_renderer.load_scene(
        parts, "perlin", port.p_lvlh_t, perlin_seed=61, look=rz.look_for(3), R_lvlh_t=port.R_lvlh_t
    )
    gl_renderer.render(*pose)
    gl_renderer.load_scene(parts, "perlin", port.p_lvlh_t, perlin_seed=61)
    assert np.array_equal(gl_renderer.render(*pose), before)


@pytest.mark.parametrize("seed", [0, 5, 11])
def test_a_randomised_frame_differs_and_keeps_the_fixtures_silhouette(gl_renderer, fixture_view, seed):
    """Against a black backdrop, without the optics: every pixel the look lights lies on the
    label pass's silhouette (grown by one pixel for edge antialiasing of nothing: MSAA is off),
    the label pass is the default look's, and the frame is not the default one."""
    parts, port, pose = fixture_view
    gl_renderer.load_scene(parts, "perlin", port.p_lvlh_t, perlin_seed=61)
    default, ids0 = gl_renderer.render(*pose), gl_renderer.render(*pose, mode="id")[..., 0]
    look = replace(rz.look_for(seed), backdrop="black", vignetting=0.0, distortion_k1=0.0)
    gl_renderer.load_scene(parts, "perlin", port.p_lvlh_t, perlin_seed=61, look=look, R_lvlh_t=port.R_lvlh_t)
    img, ids = gl_renderer.render(*pose), gl_renderer.render(*pose, mode="id")[..., 0]
    assert np.array_equal(ids, ids0)
    lit = img.max(axis=2) > 0
    assert not np.any(lit & (ids == 0)), np.argwhere(lit & (ids == 0))[:5]
    assert lit[ids > 0].mean() > 0.5  # most of the fixture is seen (the bore and shadows may be black)
    assert np.abs(img.astype(int) - default).mean() > 3.0


def test_materials_change_the_fixtures_pixels_only(gl_renderer, fixture_view):
    """Two looks that differ in their materials alone differ only on the fixture's parts that
    carry a material, and there they differ."""
    parts, port, pose = fixture_view
    a = replace(rz.look_for(21), backdrop="perlin")
    b = replace(a, materials=rz.look_for(22).materials)
    assert a.materials != b.materials
    out = []
    for lk in (a, b):
        gl_renderer.load_scene(
            parts, "perlin", port.p_lvlh_t, perlin_seed=61, look=lk, R_lvlh_t=port.R_lvlh_t
        )
        out.append(gl_renderer.render(*pose).astype(int))
    ids = gl_renderer.render(*pose, mode="id")[..., 0]
    changed = np.any(out[0] != out[1], axis=2)
    fixture = (ids >= ID_BOUNDARY) & (ids <= ID_CONNECTOR)
    grown = (
        fixture
        | np.roll(fixture, 1, 0)
        | np.roll(fixture, -1, 0)
        | np.roll(fixture, 1, 1)
        | np.roll(fixture, -1, 1)
    )
    assert not np.any(changed & ~grown)  # (a pixel beside the silhouette: the optics' resampling)
    assert changed[fixture].mean() > 0.5


def _slab_scene(port) -> list[Part]:
    """A white Lambertian slab on the berthing plane and a 10 cm cube 0.3 m in front of it."""
    T = np.block([[port.R_lvlh_t, port.p_lvlh_t[:, None]], [np.zeros((1, 3)), np.ones((1, 1))]])
    slab = trimesh.creation.box(extents=(3.0, 3.0, 0.1))
    slab.apply_translation([0.0, 0.0, 0.05])
    cube = trimesh.creation.box(extents=(0.1, 0.1, 0.1))
    cube.apply_translation([0.0, 0.0, -0.3])
    return [
        Part(slab.apply_transform(T), (0.5, 0.5, 0.5), 0.0, 2),
        Part(cube.apply_transform(T), (0.5, 0.5, 0.5), 0.0, 3),
    ]


def _facing(port, z_m: float):
    """An aligned camera z_m in front of the berthing plane, looking along +Z_t."""
    return port.R_lvlh_t, port.p_lvlh_t + port.R_lvlh_t @ np.array([0.0, 0.0, -z_m])


def _px(p_t: np.ndarray, z_m: float) -> tuple[int, int]:
    u, v = CAM.project((p_t + np.array([0.0, 0.0, z_m]))[None])[0]
    return int(v), int(u)


def test_a_lamp_lights_by_the_inverse_square_and_casts_its_own_shadow(gl_renderer):
    """One lamp fixed 1 m aside, 2 m out, no Sun: the slab beside the cube reads what a Lambertian
    surface under the lamp's irradiance (the look's at the aim point, falling with the squared
    distance and the cosine) gives, within 3 DN; the cube's shadow lands where the lamp puts it."""
    port = PORTS[1]
    lamp = rz.Lamp("world", (1.0, 0.0, -2.0), (0.0, 0.0, 0.0), 0.8, (1.0, 1.0, 1.0), 60.0, 5.0)
    look = _plain(lighting="lamp_off_camera", sun_scale=0.0, lamps=(lamp,))
    gl_renderer.load_scene(
        _slab_scene(port), "perlin", port.p_lvlh_t, perlin_seed=0, look=look, R_lvlh_t=port.R_lvlh_t
    )
    R, p = _facing(port, 3.0)
    img = gl_renderer.render(R, p, port.R_lvlh_t @ np.array([0.0, 0.0, -1.0])).astype(float).mean(axis=2)
    L = np.array(lamp.position_m)
    shadow = L + (np.array([0.0, 0.0, -0.3]) - L) * (2.0 / 1.7)  # the cube's centre cast on z = 0
    lit = np.array([-shadow[0], 0.0, 0.0])  # mirrored: in the light, off the cube's image
    assert img[_px(shadow, 3.0)] < 0.2 * img[_px(lit, 3.0)]
    d = L - lit
    E = lamp.irradiance * float(L @ L) / float(d @ d) * (-d[2] / np.linalg.norm(d))
    assert img[_px(lit, 3.0)] == pytest.approx(255 * (0.5 * E) ** (1 / 2.2), abs=3.0)


def test_the_optics_move_the_corner_as_drawn_and_keep_the_centre(gl_renderer):
    """A bright square near the top-left corner: with k1 its centroid moves by the radial model's
    displacement there (sub-pixel, within 0.1 px); vignetting v darkens it by (1 - v r^2 / r_c^2)
    ^(1/gamma) and leaves the image's centre."""
    port = PORTS[1]
    z = 2.0
    # a 12 cm square whose centre projects near (70, 50) px and another on the axis
    corner_t = np.array([(70 - CAM.cx_px) / CAM.fx_px * z, (50 - CAM.cy_px) / CAM.fy_px * z, 0.0])
    T = np.block([[port.R_lvlh_t, port.p_lvlh_t[:, None]], [np.zeros((1, 3)), np.ones((1, 1))]])
    parts = []
    for c in (corner_t, np.zeros(3)):
        sq = trimesh.creation.box(extents=(0.12, 0.12, 0.02))
        sq.apply_translation(c + np.array([0.0, 0.0, 0.01]))
        parts.append(Part(sq.apply_transform(T), (0.6, 0.6, 0.6), 0.0, 2))
    R, p = _facing(port, z)
    sun = port.R_lvlh_t @ np.array([0.0, 0.0, -1.0])
    k1 = 1.0 / (rz.CORNER_RADIUS_PX / rz.F_PX) ** 3 / rz.F_PX  # +1 px at the corner
    frames = {}
    for name, lk in (("plain", _plain()), ("k1", _plain(distortion_k1=k1)), ("vig", _plain(vignetting=0.4))):
        gl_renderer.load_scene(parts, "perlin", port.p_lvlh_t, perlin_seed=0, look=lk, R_lvlh_t=port.R_lvlh_t)
        frames[name] = gl_renderer.render(R, p, sun).astype(float).mean(axis=2)

    def centroid(img: np.ndarray) -> np.ndarray:
        w = img[:150, :150]
        v, u = np.mgrid[:150, :150] + 0.5
        return np.array([(u * w).sum(), (v * w).sum()]) / w.sum()

    c0, c1 = centroid(frames["plain"]), centroid(frames["k1"])
    x = (c0 - [CAM.cx_px, CAM.cy_px]) / CAM.fx_px
    expect = c0 + x * k1 * float(x @ x) * CAM.fx_px
    assert np.linalg.norm(c1 - expect) < 0.1, (c0, c1, expect)
    assert np.linalg.norm(c1 - c0) > 0.4
    centre = (int(CAM.cy_px), int(CAM.cx_px))
    assert abs(frames["vig"][centre] - frames["plain"][centre]) <= 1.0
    v, u = (int(c0[1]), int(c0[0]))
    r2 = float(x @ x) / (rz.CORNER_RADIUS_PX / rz.F_PX) ** 2
    assert frames["vig"][v, u] == pytest.approx(frames["plain"][v, u] * (1 - 0.4 * r2) ** (1 / 2.2), abs=1.5)
