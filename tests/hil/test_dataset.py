import json
import os
from dataclasses import replace

import numpy as np
import pytest

from oibar_hil.dataset import (
    PAPER_SEQUENCES,
    DatasetError,
    SequenceSpec,
    generate_dataset,
    plan_sequence,
    read_poses_csv,
    sha256_file,
    verify_sequence,
)

N = 5
PERLIN = PAPER_SEQUENCES[2]
ISS = PAPER_SEQUENCES[8]


@pytest.fixture(scope="module")
def tiny(tmp_path_factory, gl_renderer):
    out = tmp_path_factory.mktemp("ds")
    rep = generate_dataset(out, [PERLIN, ISS], frames_limit=N, workers=1, progress=False)
    return out, rep


def test_paper_table():
    assert len(PAPER_SEQUENCES) == 12
    assert [s.background for s in PAPER_SEQUENCES.values()].count("iss") == 6
    s8 = PAPER_SEQUENCES[8]
    assert (s8.port, s8.approach, s8.sun_elevation_deg, s8.background) == (4, "-R-bar", 146, "iss")
    with pytest.raises(ValueError):
        plan_sequence(replace(s8, approach="+V-bar"))


def test_manifest_and_poses(tiny):
    out, rep = tiny
    assert rep.rendered == 2 * N and rep.sequences_complete == 2
    for spec in (PERLIN, ISS):
        d = out / spec.name
        m = verify_sequence(d)
        assert m["seed"] == spec.seed and m["spec"]["port"] == spec.port
        assert m["generator_version"] and m["frames"] == N
        assert m["config"]["camera"]["fx_px"] == pytest.approx(583.3333, abs=1e-3)
        assert set(m["files"]) == {"poses.csv"} | {f"frames/{k:06d}.jpg" for k in range(N)}
        for name, digest in m["files"].items():
            assert sha256_file(d / name) == digest
        rows = read_poses_csv(d / "poses.csv")
        plan = plan_sequence(spec, N)
        assert len(rows) == N
        for k, row in enumerate(rows):
            T = [float(row[c]) for c in ("tx_m", "ty_m", "tz_m")]
            q = [float(row[c]) for c in ("qw", "qx", "qy", "qz")]
            np.testing.assert_allclose(T, plan.T_cam_target[k], atol=1e-6)
            np.testing.assert_allclose(q, plan.q_cam_target[k], atol=1e-8)
            assert float(row["range_m"]) == pytest.approx(np.linalg.norm(T), abs=1e-5)
            assert row["phase"] == "1" and float(row["time_s"]) == pytest.approx(0.1 * k)


def test_same_seed_same_bytes_across_worker_counts(tiny, tmp_path):
    out, _ = tiny
    generate_dataset(tmp_path, [PERLIN], frames_limit=N, workers=2, progress=False)
    a = json.loads((out / PERLIN.name / "manifest.json").read_text())["files"]
    b = json.loads((tmp_path / PERLIN.name / "manifest.json").read_text())["files"]
    assert a == b


def test_truncated_or_corrupt_frame_is_detected(tiny, tmp_path):
    out, _ = tiny
    generate_dataset(tmp_path, [PERLIN], frames_limit=N, workers=1, progress=False)
    d = tmp_path / PERLIN.name
    f2 = d / "frames/000002.jpg"
    f2.write_bytes(f2.read_bytes()[:-100])
    with pytest.raises(DatasetError, match=r"000002\.jpg: truncated"):
        verify_sequence(d)
    f2.write_bytes((out / PERLIN.name / "frames/000002.jpg").read_bytes())
    verify_sequence(d)
    f3 = d / "frames/000003.jpg"
    data = bytearray(f3.read_bytes())
    data[len(data) // 2] ^= 0xFF
    f3.write_bytes(bytes(data))
    with pytest.raises(DatasetError, match=r"000003\.jpg: corrupt"):
        verify_sequence(d)


def test_resume_skips_finished_frames(tiny, tmp_path):
    out, _ = tiny
    d = tmp_path / PERLIN.name
    generate_dataset(tmp_path, [PERLIN], frames_limit=N, workers=1, progress=False)
    # Simulate an interruption: manifest not yet written, one frame missing, one cut short.
    (d / "manifest.json").unlink()
    (d / "frames/000001.jpg").unlink()
    f3 = d / "frames/000003.jpg"
    f3.write_bytes(f3.read_bytes()[:500])
    kept = {k: os.stat(d / f"frames/{k:06d}.jpg").st_mtime_ns for k in (0, 2, 4)}
    rep = generate_dataset(tmp_path, [PERLIN], frames_limit=N, workers=1, progress=False)
    assert rep.rendered == 2 and rep.skipped == N - 2
    for k, t in kept.items():
        assert os.stat(d / f"frames/{k:06d}.jpg").st_mtime_ns == t
    m = verify_sequence(d)
    assert m["files"] == json.loads((out / PERLIN.name / "manifest.json").read_text())["files"]
    # A complete sequence is skipped entirely.
    rep2 = generate_dataset(tmp_path, [PERLIN], frames_limit=N, workers=1, progress=False)
    assert rep2.rendered == 0 and rep2.skipped == N


def test_resume_refuses_a_different_spec(tmp_path, gl_renderer):
    generate_dataset(tmp_path, [PERLIN], frames_limit=2, workers=1, progress=False)
    other = replace(PERLIN, seed=PERLIN.seed + 1)
    with pytest.raises(DatasetError, match="different sequence spec"):
        generate_dataset(tmp_path, [other], frames_limit=2, workers=1, progress=False)


def test_custom_spec_png_envelope(tmp_path, gl_renderer):
    spec = SequenceSpec(
        name="custom",
        port=5,
        approach="+R-bar",
        sun_elevation_deg=100,
        background="perlin",
        seed=77,
        envelope=True,
        image_format="png",
        noise_sigma_dn=2.0,
        blur_sigma_px=0.7,
    )
    generate_dataset(tmp_path, [spec], frames_limit=2, workers=1, progress=False)
    m = verify_sequence(tmp_path / "custom")
    assert "frames/000001.png" in m["files"] and m["spec"]["envelope"] is True


def test_renderers_survive_other_gl_contexts_in_the_process(gl_renderer, tmp_path):
    """The dataset writer caches its renderer per process. Another GL context made and released
    in between (a test's, a rig camera's) used to leave none current, and the next frame crashed
    inside the driver (SIGSEGV). Run in a child so a crash is a failure, not a dead test run."""
    import subprocess
    import sys

    script = f"""
from pathlib import Path
from oibar_hil.dataset import PAPER_SEQUENCES, generate_dataset
from oibar_hil.render import Renderer
def gen(name):
    return generate_dataset(Path({str(tmp_path)!r}) / name, [PAPER_SEQUENCES[2]], frames_limit=2,
                            workers=1, progress=False).rendered
assert gen("a") == 2
Renderer().release()
other = Renderer()          # and one left alive, current
assert gen("b") == 2
other.release()
print("ok")
"""
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0 and proc.stdout.strip().endswith("ok"), (proc.returncode, proc.stderr[-2000:])


def _crash_once(task: dict) -> int:
    """A render chunk whose worker dies the first time (as Mesa once did with SIGSEGV)."""
    import os
    from pathlib import Path

    marker = Path(task["marker"])
    if task["crash"] and not marker.exists():
        marker.write_text("crashed")
        os._exit(139)
    (marker.parent / f"done_{task['i']}").write_text("ok")
    return 1


def test_a_dying_render_worker_does_not_hang_the_writer(tmp_path):
    """multiprocessing.Pool waits forever for a chunk whose worker died; the writer must restart
    the pool and finish every chunk, then stop with a clear error when workers keep dying."""
    from oibar_hil.dataset import _render_in_pool

    tasks = [{"i": i, "crash": i == 3, "marker": str(tmp_path / "marker")} for i in range(8)]
    _render_in_pool(tasks, 2, 2, None, fn=_crash_once)
    assert sorted(p.name for p in tmp_path.glob("done_*")) == [f"done_{i}" for i in range(8)]


def _crash_always(task: dict) -> int:
    import os

    os._exit(139)


def test_workers_that_keep_dying_give_a_clear_error(tmp_path):
    from oibar_hil.dataset import POOL_RESTARTS, DatasetError, _render_in_pool

    with pytest.raises(DatasetError, match=f"kept dying \\({POOL_RESTARTS + 1} pools\\); 1 chunk"):
        _render_in_pool([{"i": 0}], 1, 1, None, fn=_crash_always)


def test_frame_stride_keeps_every_nth_pose_and_old_specs_keep_their_identity():
    from oibar_hil.dataset import spec_dict

    full = plan_sequence(PAPER_SEQUENCES[2])
    every8 = plan_sequence(replace(PAPER_SEQUENCES[2], frame_stride=8))
    assert every8.n_frames == (full.n_frames + 7) // 8
    assert np.allclose(every8.T_cam_target, full.T_cam_target[::8])
    assert np.allclose(every8.t_s, full.t_s[::8]) and np.allclose(every8.sun_lvlh[1], full.sun_lvlh[8])
    assert "frame_stride" not in spec_dict(PAPER_SEQUENCES[2])  # datasets written before it match
    assert spec_dict(replace(PAPER_SEQUENCES[2], frame_stride=8))["frame_stride"] == 8
    with pytest.raises(ValueError, match="frame_stride"):
        replace(PAPER_SEQUENCES[2], frame_stride=0).validate()


def test_shards_split_the_scene_list_disjointly():
    from oibar_hil.dataset import shard

    specs = [PAPER_SEQUENCES[n] for n in range(1, 13)]
    parts = [shard(specs, f"{i}/5") for i in range(5)]
    assert sorted(s.name for p in parts for s in p) == sorted(s.name for s in specs)
    assert [s.name for s in parts[1]] == ["seq02", "seq07", "seq12"]
    for bad in ("5/5", "x", "1/0", "-1/3"):
        with pytest.raises(ValueError, match="--shard"):
            shard(specs, bad)


def test_scene_spec_files_name_paper_sequences_and_refuse_bad_entries(tmp_path):
    from oibar_hil.dataset import load_spec_file

    p = tmp_path / "s.json"
    p.write_text(
        json.dumps(
            {
                "scenes": [
                    {"paper": 8},
                    {
                        "name": "a",
                        "port": 5,
                        "approach": "+R-bar",
                        "sun_elevation_deg": 90,
                        "background": "iss",
                        "seed": 3,
                    },
                ]
            }
        )
    )
    assert [s.name for s in load_spec_file(p)] == ["seq08", "a"]
    p.write_text(
        json.dumps(
            {
                "scenes": [
                    {
                        "name": "a",
                        "port": 5,
                        "approach": "-V-bar",
                        "sun_elevation_deg": 90,
                        "background": "iss",
                        "seed": 3,
                    }
                ]
            }
        )
    )
    with pytest.raises(DatasetError, match="scene 0: a: port 5 is a \\+R-bar port"):
        load_spec_file(p)
    p.write_text(json.dumps({"scenes": [{"paper": 2}, {"paper": 2}]}))
    with pytest.raises(DatasetError, match="used twice"):
        load_spec_file(p)
    p.write_text("{not json")
    with pytest.raises(DatasetError, match="cannot read"):
        load_spec_file(p)


def test_a_sequence_drawn_by_the_second_renderer(tmp_path):
    """A spec can name Mitsuba and a look: the writer draws it with the path tracer, each frame's
    samples seeded by the frame (so a re-render gives the same bytes, whichever worker drew it),
    and the renderer is part of the sequence's identity; a lab look needs the path tracer, and
    the fields left at their defaults keep the identity of the data sets written before them."""
    from oibar_hil.dataset import spec_dict

    spec = replace(PERLIN, name="mi", renderer="mitsuba", look="lab", mitsuba_spp=2, frame_stride=200)
    generate_dataset(tmp_path / "a", [spec], frames_limit=2, workers=1, progress=False)
    generate_dataset(tmp_path / "b", [spec], frames_limit=2, workers=1, progress=False)
    fa = sorted((tmp_path / "a" / "mi" / "frames").iterdir())
    fb = sorted((tmp_path / "b" / "mi" / "frames").iterdir())
    assert len(fa) == 2 and [f.read_bytes() for f in fa] == [f.read_bytes() for f in fb]
    img = np.asarray(__import__("PIL.Image", fromlist=["Image"]).open(fa[0]).convert("RGB"))
    assert img.max() > 60 and np.median(img) < 5  # a lit grey fixture on black
    ident = json.loads((tmp_path / "a" / "mi" / "spec.json").read_text())
    assert ident["renderer"] == "mitsuba" and ident["look"] == "lab"
    assert "renderer" not in spec_dict(PERLIN) and "look" not in spec_dict(PERLIN)
    with pytest.raises(ValueError, match="lab with the mitsuba renderer"):
        replace(PERLIN, look="lab").validate()
    with pytest.raises(ValueError, match="renderer must be"):
        replace(PERLIN, renderer="blender").validate()
