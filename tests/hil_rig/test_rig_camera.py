"""The HIL rig's rendered camera (oibar_hil.rig.camera): same frames as the synthetic dataset
for the same pose and time, and the fixture where the pinhole model puts it."""

import json
import threading
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from oibar.geometry.docking import GEOMETRY, MOUNT, docking_from_camera_pose
from oibar.geometry.fixture import FIXTURE, fixture_corners_t
from oibar.geometry.rotations import quat_to_matrix
from oibar.geometry.transforms import transform_points
from oibar_hil import dataset
from oibar_hil.dataset import PAPER_SEQUENCES, plan_sequence
from oibar_hil.meshes import (
    ID_BOUNDARY,
    ID_CONNECTOR,
    ID_COUPLING,
    ID_DROGUE,
    ID_PIN_GUIDE,
    ID_PLATE,
    end_effector,
)
from oibar_hil.ports import PORTS
from oibar_hil.rig.camera import OrbitClock, RigCamera, RigCameraError, pose_to_lvlh, scene_spec

REPO = Path(__file__).resolve().parents[2]

SEQ01 = PAPER_SEQUENCES[1]  # iss background, port 1 (+V-bar): the default scene
SEQ07 = PAPER_SEQUENCES[7]  # perlin background, port 4 (-R-bar): another port, approach and backdrop
FACE = {ID_PLATE, ID_PIN_GUIDE, ID_COUPLING, ID_CONNECTOR}  # the fixture's face around the drogue
# A randomised look (issue 58 part 3) on a fixture-only scene (quick to load): two lamps riding on
# the camera and one fixed in F_t, a Perlin backdrop, vignetting, lens distortion, exposure 1.5.
DR070 = f"{REPO / 'models/scenes/train_dr.json'}:dr070"


@pytest.fixture(scope="module")
def cam(headless_gl):
    c = RigCamera(scene="seq01")
    yield c
    c.close()


@pytest.fixture(scope="module")
def plans():
    # Whole plans (labels and orbit for every frame, ~0.5 s each), so the frames below can be
    # taken from the far, middle and close ranges; only the chosen frames are rendered.
    return {s.name: plan_sequence(s) for s in (SEQ01, SEQ07)}


# ----------------------------------------------------------------------------- no GL needed
def test_unknown_scene_is_a_clear_error():
    with pytest.raises(RigCameraError, match="unknown scene 'seq13'.*seq01"):
        RigCamera(scene="seq13")
    with pytest.raises(RigCameraError, match="unknown scene"):
        RigCamera(scene=1)


def test_a_scene_set_files_scene_can_be_the_loops_look(tmp_path):
    from oibar_hil.rig.camera import scene_spec

    val = REPO / "models/scenes/val.json"
    spec = scene_spec(f"{val}:va013")
    stored = next(s for s in json.loads(val.read_text())["scenes"] if s["name"] == "va013")
    assert (spec.name, spec.port, spec.sun_elevation_deg, spec.background, spec.turned_deg) == (
        "va013",
        stored["port"],
        stored["sun_elevation_deg"],
        stored["background"],
        stored["turned_deg"],
    )
    with pytest.raises(RigCameraError, match="unknown scene 'va999' in .*va000"):
        scene_spec(f"{val}:va999")
    with pytest.raises(RigCameraError, match="cannot read the scene spec"):
        scene_spec(f"{tmp_path / 'missing.json'}:va000")
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"scenes": [{"name": "x1", "port": 9}]}))
    with pytest.raises(RigCameraError, match="scene 0"):
        scene_spec(f"{bad}:x1")


def test_a_mitsuba_scene_is_refused_with_what_to_use_instead():
    """The lab look and the matched validation looks are the Mitsuba path tracer's; the rig camera
    rasterises, so it says so before any GL work rather than fly the loop on another image."""
    lab = f"{REPO / 'models/scenes/val_lab.json'}:va000"
    mitsuba_set = REPO / "models/scenes/val_mitsuba.json"
    matched = f"{mitsuba_set}:{json.loads(mitsuba_set.read_text())['scenes'][0]['name']}"
    for scene in (lab, matched, scene_spec(f"{REPO / 'models/scenes/val.json'}:va000")):
        if not isinstance(scene, str):
            scene = replace(scene, renderer="mitsuba", look="lab")
        with pytest.raises(RigCameraError, match=r"Mitsuba path tracer.*fly a raster scene") as e:
            RigCamera(scene=scene)
        assert "\n" not in str(e.value)
    # the raster scene of the same name flies
    assert scene_spec(f"{REPO / 'models/scenes/val.json'}:va000").renderer == "raster"
    # A randomised look draws its own exposure: a dispersed one would be silently ignored.
    with pytest.raises(RigCameraError, match="randomized look.*exposure=2.0 would be ignored"):
        RigCamera(scene=DR070, exposure=2.0)


def test_mount_and_probe_have_one_source():
    assert MOUNT.p_s_cam_m == tuple(GEOMETRY.p_s_cam_m)
    np.testing.assert_array_equal(np.asarray(MOUNT.R_s_cam), GEOMETRY.R_s_cam)
    # The probe tip of the end-effector mesh (F_s, +z towards the target) is GEOMETRY's.
    probe = end_effector()[-1].mesh
    assert probe.vertices[:, 2].max() == pytest.approx(GEOMETRY.probe_tip_s_m, abs=1e-6)


@pytest.mark.parametrize("name", ["seq01", "seq07"])
def test_pose_and_orbit_clock_match_the_dataset_plan(plans, name):
    """Label -> (r_D, att) -> camera pose in LVLH, Sun and Earth at the frame's time: the
    numbers the dataset renders with, to rounding."""
    plan = plans[name]
    clock = OrbitClock(plan.spec)
    port = PORTS[plan.spec.port]
    for k in list(range(0, 40)) + [plan.n_frames // 2, plan.n_frames - 1]:
        st = docking_from_camera_pose(plan.T_cam_target[k], quat_to_matrix(plan.q_cam_target[k]))
        R_l_c, p_l_c, T, R = pose_to_lvlh(st.r_D_m, st.att_rad, port)
        np.testing.assert_allclose(T, plan.T_cam_target[k], atol=1e-12)
        np.testing.assert_allclose(R_l_c, plan.R_lvlh_cam[k], atol=1e-12)
        np.testing.assert_allclose(p_l_c, plan.p_lvlh_cam[k], atol=1e-12)
        sun, R_ecef = clock.at(plan.t_s[k])
        np.testing.assert_array_equal(sun, plan.sun_lvlh[k])
        np.testing.assert_array_equal(R_ecef, plan.R_ecef_lvlh[k])
    np.testing.assert_array_equal(clock.earth_center_lvlh_km, plan.earth_center_lvlh_km)


# ----------------------------------------------------------------------------- rendering
def _dataset_frame(plan, k: int, tmp: Path) -> np.ndarray:
    """Frame k as the dataset generator writes it (its own worker renderer and file path) and
    as the training loader decodes it."""
    # Enter the worker renderer's context before the generator (re)loads a scene with it: the
    # rig camera's context may have been used in this thread since.
    r = dataset._WORKER.get("renderer") or dataset._renderer_for(plan.spec)
    task = {
        "spec": plan.spec,
        "seq_dir": str(tmp),
        "frames": [k],
        "R_lvlh_cam": plan.R_lvlh_cam[[k]],
        "p_lvlh_cam": plan.p_lvlh_cam[[k]],
        "sun_lvlh": plan.sun_lvlh[[k]],
        "R_ecef_lvlh": plan.R_ecef_lvlh[[k]],
        "earth_center_lvlh_km": plan.earth_center_lvlh_km,
    }
    (tmp / "frames").mkdir(exist_ok=True)
    with r.ctx:
        dataset._render_chunk(task)
    with Image.open(tmp / dataset.frame_name(k, plan.spec.image_format)) as im:
        return np.asarray(im.convert("RGB"), dtype=np.uint8)


@pytest.fixture(scope="module")
def dataset_renderer():
    """A fresh generator worker renderer for these tests (an earlier test may have left one
    with other settings), and the module's state put back afterwards."""
    saved = dict(dataset._WORKER)
    dataset._WORKER.clear()
    yield
    r = dataset._WORKER.get("renderer")
    if r is not None:
        r.release()
    dataset._WORKER.clear()
    dataset._WORKER.update(saved)


@pytest.mark.slow
@pytest.mark.parametrize("name, where", [("seq01", 0.0), ("seq01", 0.5), ("seq01", 1.0), ("seq07", 1.0)])
def test_same_frame_as_the_dataset(cam, plans, dataset_renderer, tmp_path, name, where):
    """The rig camera, driven by the rig's state for a dataset frame, gives that frame.

    Tolerance: the two paths feed the same renderer and JPEG encoder; the only difference is
    the pose's round trip through the docking frame (~1e-16 m), which may flip the coverage of
    a rare edge pixel after the float32 conversion, and JPEG then spreads that within its 8x8
    block. So at most 0.1 % of pixels may differ and the mean difference stays under 0.05 DN;
    a wrong pose, Sun, Earth or background moves thousands of pixels. (On llvmpipe the frames
    have been bit-identical.)"""
    plan = plans[name]
    k = int(round(where * (plan.n_frames - 1)))
    c = cam if name == "seq01" else RigCamera(scene=name)
    try:
        st = docking_from_camera_pose(plan.T_cam_target[k], quat_to_matrix(plan.q_cam_target[k]))
        got = c.render(st.r_D_m, st.att_rad, t_s=float(plan.t_s[k]))
    finally:
        if c is not cam:
            c.close()
    want = _dataset_frame(plan, k, tmp_path)
    assert got.image.shape == (480, 744, 3) and got.image.dtype == np.uint8
    np.testing.assert_allclose(got.T_cam_target_m, plan.T_cam_target[k], atol=1e-12)
    diff = np.abs(got.image.astype(np.int16) - want.astype(np.int16))
    assert np.count_nonzero(diff.max(axis=2)) <= 0.001 * 480 * 744, f"frame {k} ({plan.range_m[k]:.2f} m)"
    assert diff.mean() < 0.05
    # Not a vacuous match: the frame has content (the fixture and a backdrop), not a black image.
    assert want.std() > 5.0


def test_a_randomized_look_is_the_datasets_frame(headless_gl, dataset_renderer, tmp_path):
    """A scene with look "randomized" (models/scenes/train_dr.json:dr070) gives, at a data-set
    frame's pose and time, the generator's frame for the same spec and index: the same LookParams
    (materials, lamps that follow the camera, backdrop, exposure, optics) and the same JPEG
    round trip. Two frames, far (the first) and close (the last); the tolerance is
    test_same_frame_as_the_dataset's (on llvmpipe the frames have been bit-identical)."""
    spec = scene_spec(DR070)
    look = dataset.spec_look(spec)
    assert look is not None and spec.background == "perlin"
    assert "camera" in {lamp.mount for lamp in look.lamps} and look.vignetting > 0 and look.distortion_k1 != 0
    plan = plan_sequence(spec)
    ks = (0, plan.n_frames - 1)
    got = {}
    with RigCamera(scene=DR070) as c:
        assert c.spec == spec
        for k in ks:
            st = docking_from_camera_pose(plan.T_cam_target[k], quat_to_matrix(plan.q_cam_target[k]))
            got[k] = c.render(st.r_D_m, st.att_rad, t_s=float(plan.t_s[k])).image
    for k in ks:
        want = _dataset_frame(plan, k, tmp_path)
        diff = np.abs(got[k].astype(np.int16) - want.astype(np.int16))
        assert np.count_nonzero(diff.max(axis=2)) <= 0.001 * 480 * 744, f"frame {k} ({plan.range_m[k]:.2f} m)"
        assert diff.mean() < 0.05
        assert want.std() > 5.0
    # Not the matched look under another name: the same spec's matched frame is another image.
    with RigCamera(scene=replace(spec, look="matched")) as m:
        st = docking_from_camera_pose(plan.T_cam_target[0], quat_to_matrix(plan.q_cam_target[0]))
        matched = m.render(st.r_D_m, st.att_rad, t_s=float(plan.t_s[0])).image
    assert np.abs(matched.astype(np.int16) - got[0].astype(np.int16)).mean() > 5.0


# (r_D_m, att_rad): on the axis at 5 m; offset, misaligned and rolled at 2 m; close with roll.
POSES = [
    (np.array([0.0, 0.0, 5.0]), np.zeros(3)),
    (np.array([0.15, -0.10, 2.0]), np.radians([3.0, -4.0, 10.0])),
    (np.array([0.01, 0.0, 0.35]), np.radians([0.5, 1.0, -20.0])),
]


@pytest.mark.parametrize("pose", range(len(POSES)))
def test_fixture_lands_where_the_pinhole_model_says(cam, pose):
    """Part ids of the rendered view against the projection of the frame's label: the drogue
    mouth is centred on the projected F_t origin and the rim spans the projected corners."""
    r_D, att = POSES[pose]
    frame = cam.render(r_D, att)
    ids = cam.render_ids(r_D, att)
    T, R = frame.T_cam_target_m, frame.R_cam_target

    def ids_at(points_t):
        uv = cam.camera.project(transform_points(points_t, R, T))
        return ids[np.floor(uv[:, 1]).astype(int), np.floor(uv[:, 0]).astype(int)]

    # Through the mouth (F_t origin, and 0.7 mouth radii around it) one sees into the drogue
    # (the port adapter behind the plate leaves its room free since generator 0.2.0); 1.35 radii
    # out, just beyond the drogue's lip (1.21 radii), one sees the fixture's face. A mouth more
    # than ~0.15 radii (14 mm) off the projected origin puts some of the outer points on the
    # lip or into the mouth.
    a = np.linspace(0.0, 2 * np.pi, 16, endpoint=False)
    ring = np.stack([np.cos(a), np.sin(a), np.zeros_like(a)], axis=1) * FIXTURE.drogue_mouth_radius_m
    inner = np.vstack([[0.0, 0.0, 0.0], 0.7 * ring])
    outer = 1.35 * ring + [0.0, 0.0, FIXTURE.rim_depth_m]
    assert set(ids_at(inner)) == {ID_DROGUE}, ids_at(inner)
    assert set(ids_at(outer)) <= FACE, ids_at(outer)
    assert ID_PLATE in set(ids_at(outer))

    # The rim's pixels span the projected outer corners (front face, z = 0) to a pixel.
    rows, cols = np.nonzero(ids == ID_BOUNDARY)
    uv = cam.camera.project(transform_points(fixture_corners_t(), R, T))
    np.testing.assert_allclose(
        [cols.min(), cols.max() + 1, rows.min(), rows.max() + 1],
        [uv[:, 0].min(), uv[:, 0].max(), uv[:, 1].min(), uv[:, 1].max()],
        atol=1.0,
    )

    # The shaded frame agrees: the rim (dark anodised, rgb 0.10) is darker than the plate (0.72).
    img = frame.image.astype(float).mean(axis=2)
    assert np.median(img[ids == ID_BOUNDARY]) < np.median(img[ids == ID_PLATE])


THROAT_VIEWS = [  # probe tip in D (m), attitude (rad): on the axis, off it, off it and turned
    (np.array([0.0, 0.0, 1.0]), np.zeros(3)),
    (np.array([0.30, -0.20, 1.0]), np.zeros(3)),
    (np.array([-0.25, 0.15, 2.5]), np.radians([2.0, -1.5, 0.0])),
    (np.array([0.40, 0.30, 4.0]), np.zeros(3)),
]


@pytest.mark.parametrize("view", range(len(THROAT_VIEWS)))
def test_the_throat_keypoint_is_seen_where_it_projects(cam, view):
    """The drogue's throat (FIXTURE_KEYPOINTS' drogue_throat, 0.18 m deep, the one keypoint off
    the berthing plane) is a dark opening at the funnel's bottom, and from the axis or off it the
    pixel where the label projects it shows that opening. With generator 0.1.0 a solid port
    adapter crossed the funnel 5 cm deep: the label's pixel showed the adapter's face, so a
    network could only learn the funnel's centre, which moves with the view differently."""
    r_D, att = THROAT_VIEWS[view]
    frame = cam.render(r_D, att)
    ids = cam.render_ids(r_D, att)
    uv = cam.camera.project(
        transform_points(np.array([[0.0, 0.0, 0.18]]), frame.R_cam_target, frame.T_cam_target_m)
    )
    u, v = np.floor(uv[0]).astype(int)
    assert ids[v, u] == ID_DROGUE, ids[v - 2 : v + 3, u - 2 : u + 3]
    img = frame.image.astype(float).mean(axis=2)
    funnel = img[ids == ID_DROGUE]
    assert img[v, u] < np.percentile(funnel, 10), (img[v, u], np.percentile(funnel, [10, 50]))


def test_renders_from_another_thread(cam):
    """host/oibar/camera's LatestFrame calls the source from its reader thread."""
    r_D, att = POSES[1]
    here = cam.render(r_D, att, t_s=3.0).image
    out = {}
    t = threading.Thread(target=lambda: out.setdefault("img", cam.render(r_D, att, t_s=3.0).image))
    t.start()
    t.join(60)
    np.testing.assert_array_equal(out["img"], here)


def test_frames_are_numbered_and_closed_camera_refuses(headless_gl):
    c = RigCamera(scene="seq07", sensor_effects=False)
    with c:
        f0 = c.render(np.array([0.0, 0.0, 3.0]), np.zeros(3), t_s=0.0)
        f1 = c.render(np.array([0.0, 0.0, 3.0]), np.zeros(3), t_s=0.1)
        assert (f0.frame, f1.frame, f1.t_s) == (0, 1, 0.1)
        # Raw rasteriser output is deterministic: the same pose and Sun sample, the same pixels.
        np.testing.assert_array_equal(f0.image, f1.image)
    assert c.closed
    with pytest.raises(RigCameraError, match="finite"):
        pose_to_lvlh(np.array([0.0, np.nan, 3.0]), np.zeros(3), PORTS[1])
    with pytest.raises(RigCameraError, match="closed"):
        c.render(np.array([0.0, 0.0, 3.0]), np.zeros(3))
