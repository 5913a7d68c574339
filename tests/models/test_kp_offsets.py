"""oibar_models.kp_offsets: where the keypoint network puts each keypoint, the window placed by
the truth. A frame enlarged about the fixture's centre must read outward by the enlargement; the
frame as rendered must not."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from PIL import Image

from oibar.geometry.rotations import quat_to_matrix
from oibar.nav.keypoints import project
from oibar.nav.pose import PoseEstimator
from oibar_models import kp_offsets as O
from oibar_models.kp_evaluate import SETS

ROOT = Path(__file__).resolve().parents[2]
MODEL = ROOT / "models" / "oibarnet.onnx"
GOLDEN = ROOT / "tests" / "golden" / "pose"


def test_radial_offsets_of_a_scaled_pattern_are_its_scale():
    rng = np.random.default_rng(0)
    uv = rng.uniform(100, 300, (12, 2))
    uv = np.vstack([uv, uv.mean(0)])  # one on the centroid: no direction, no share
    c = uv.mean(0)
    radial, rel = O.radial_offsets(c + 1.05 * (uv - c), uv)
    assert np.allclose(rel[:-1], 0.05) and np.isnan(rel[-1])
    assert np.allclose(radial[:-1], 0.05 * np.linalg.norm(uv[:-1] - c, axis=1))
    radial, rel = O.radial_offsets(
        uv + [3.0, 0.0], uv
    )  # a shift is not a scale: outward one side, in the other
    assert np.nanmean(rel) == pytest.approx(0.0, abs=0.01) and radial.min() < -1 and radial.max() > 1


@pytest.mark.parametrize("frame", ["cold_3m", "cold_8m"])
def test_a_frame_enlarged_about_the_fixture_reads_outward_by_the_enlargement(frame):
    gold = json.loads((GOLDEN / "golden.json").read_text())
    pose = next(p for p in gold["poses"] if p["frame"] == frame)
    T, R = np.array(pose["T_cam_target_m"]), quat_to_matrix(np.array(pose["q_cam_target"]))
    img = np.asarray(Image.open(GOLDEN / f"{frame}.png").convert("RGB"))
    reader = PoseEstimator(MODEL, threads=1).reader
    as_drawn = O.read_offsets(reader, img, R, T)
    assert as_drawn is not None
    assert abs(np.nanmedian(as_drawn["rel"])) < 0.01
    c = project(reader.K_frame, reader.points_m, R, T).mean(0)
    big = cv2.warpAffine(
        img, cv2.getRotationMatrix2D((float(c[0]), float(c[1])), 0.0, 1.06), img.shape[1::-1]
    )
    enlarged = O.read_offsets(reader, big, R, T)
    assert enlarged is not None
    assert 0.04 < np.nanmedian(enlarged["rel"]) < 0.08
    assert np.nanmedian(enlarged["radial_crop_px"]) > np.nanmedian(as_drawn["radial_crop_px"]) + 1.0


def test_the_cli_writes_its_table_and_refuses_what_it_cannot_read(tmp_path, tiny_dataset, monkeypatch):
    monkeypatch.setenv("OIBAR_TRACKING", "0")
    (tmp_path / "val.json").write_text(json.dumps({"scenes": [{"paper": 3}]}))
    monkeypatch.setitem(SETS, "val", (str(tmp_path / "val.json"), str(tiny_dataset)))
    out = tmp_path / "out"
    argv = ["--sets", "val", "--min-range-m", "1", "--max-range-m", "5", "--out", str(out), "--no-progress"]
    assert O.main(argv) == 0
    got = json.loads((out / "offsets.json").read_text())
    assert got["counts"]["val"] == 48 and len(got["per_set"]["val"]) == len(
        PoseEstimator(MODEL).reader.points_m
    )
    assert (out / "offsets.png").stat().st_size > 0 and "rim_top_left" in (out / "offsets.md").read_text()
    assert (
        O.main([*argv[:2], "--min-range-m", "20", "--max-range-m", "30", "--out", str(out)]) == 2
    )  # no frames
    monkeypatch.setitem(SETS, "val", (str(tmp_path / "val.json"), str(tmp_path / "nowhere")))
    assert O.main(argv) == 2  # not rendered


def _with_look(src: Path, dst: Path, lighting: str, rim: dict, plate: dict) -> None:
    import shutil

    shutil.copytree(src, dst)
    m = json.loads((dst / "manifest.json").read_text())
    m["config"]["look"] = {
        "lighting": lighting,
        "backdrop": "black",
        "materials": [["rim", rim], ["plate", plate]],
    }
    (dst / "manifest.json").write_text(json.dumps(m))


def test_randomised_looks_are_grouped_by_lamps_and_the_rims_contrast(tmp_path, tiny_dataset, monkeypatch):
    monkeypatch.setenv("OIBAR_TRACKING", "0")
    grey = {"kind": "print_grey", "rgb": [0.55, 0.55, 0.55]}
    built = {"kind": "as_built", "rgb": [0.0, 0.0, 0.0]}  # as the manifest writes it: its own colour
    looks = tmp_path / "looks"
    looks.mkdir()
    _with_look(tiny_dataset / "seq02", looks / "dr000", "lamp_at_camera", grey, grey)  # the lab's
    _with_look(tiny_dataset / "seq03", looks / "dr001", "sun", built, built)  # ours
    out = tmp_path / "out"
    argv = ["--by-look", str(looks), "--min-range-m", "1", "--max-range-m", "5", "--stride", "4"]
    assert O.main([*argv, "--out", str(out), "--no-progress"]) == 0
    got = json.loads((out / "by_look.json").read_text())
    rows = {r["sequence"]: r for r in got["sequences"]}
    assert rows["dr000"]["lamps"] and not rows["dr000"]["dark_rim"] and rows["dr000"]["rim_contrast"] == 0.0
    assert not rows["dr001"]["lamps"] and rows["dr001"]["dark_rim"] and rows["dr001"]["rim_contrast"] > 0.5
    counts = {(g["light"], g["rim"]): g["sequences"] for g in got["groups"]}
    assert counts == {
        ("Sun / Earth", "darker than the plate"): 1,
        ("Sun / Earth", "about as light as the plate"): 0,
        ("lamps", "darker than the plate"): 0,
        ("lamps", "about as light as the plate"): 1,
    }
    assert (out / "by_look.png").stat().st_size > 0
    # a folder of sequences without a randomised look: one line, exit 2
    assert O.main(["--by-look", str(tiny_dataset), "--out", str(out), "--no-progress"]) == 2
