"""The head's crop-gain measurement (oibar_models.kp_head_crop_gain): the fit parts a view's gain
from the bearing's leak, bins by range, refuses what the flight code would, and its command line
refuses bad input before it renders anything."""

from __future__ import annotations

import json

import numpy as np
import pytest

from oibar_models.kp_head_crop_gain import (
    HeadCropGainError,
    bin_ranges_m,
    fit_bin,
    gain_table,
    main,
)


def _rows(
    g_by_range: dict[float, tuple[float, float]], scenes: int = 4, noise_deg: float = 0.05, seed: int = 0
):
    """Probe-like frames: per (scene, range) a constant lean, 9 sideways steps (truth and bearing
    move together) and 9 turns (the bearing alone), the head reading g * truth + k * bearing."""
    rng = np.random.default_rng(seed)
    out = {k: [] for k in ("range_m", "group", "head_deg", "true_deg", "bearing_deg")}
    gid = 0
    for r, (g, k) in g_by_range.items():
        for _ in range(scenes):
            lean = rng.normal(0, 1, 2)
            steps = [0.0, -1, -0.5, 0.5, 1]
            for kind in ("lateral", "turn"):
                for s, ax in [(0.0, 0)] + [(s, a) for a in (0, 1) for s in steps[1:]]:
                    v = np.zeros(2)
                    v[ax] = s * 3.4
                    true = v if kind == "lateral" else np.zeros(2)
                    bearing = v if kind == "lateral" else 3.0 / 3.4 * v
                    out["range_m"].append(r)
                    out["group"].append(gid)
                    out["true_deg"].append(true)
                    out["bearing_deg"].append(bearing)
                    out["head_deg"].append(g * true + k * bearing + lean + rng.normal(0, noise_deg, 2))
            gid += 1
    return {k: np.array(v) for k, v in out.items()}


def test_the_fit_parts_the_views_gain_from_the_bearings_leak():
    rows = _rows({3.0: (0.64, -0.073)})
    b = fit_bin(rows["group"], rows["head_deg"], rows["true_deg"], rows["bearing_deg"])
    assert b["gain"] == pytest.approx(0.64, abs=3 * b["gain_se"] + 1e-3)
    assert b["bearing_leak"] == pytest.approx(-0.073, abs=3 * b["bearing_leak_se"] + 1e-3)
    assert 0 < b["gain_se"] < 0.02 and b["resid_rms_deg"] == pytest.approx(0.05, rel=0.3)


def test_sideways_steps_alone_cannot_part_them():
    rows = _rows({3.0: (0.64, -0.073)})
    lateral = np.any(rows["true_deg"] != 0, axis=1)
    with pytest.raises(HeadCropGainError, match="do not vary apart"):
        fit_bin(
            rows["group"][lateral],
            rows["head_deg"][lateral],
            rows["true_deg"][lateral],
            rows["bearing_deg"][lateral],
        )


def test_the_table_has_one_gain_and_leak_per_range_bin_and_the_flight_codes_limits():
    from oibar.nav.error_models import HeadCropGainModel

    rows = _rows({0.5: (0.62, -0.16), 0.75: (0.62, -0.16), 3.0: (0.64, -0.07), 4.0: (0.64, -0.07)})
    out = gain_table(rows, (0.0, 1.0, 100.0), min_frames=50)
    t = out["head_crop_gain"]
    HeadCropGainModel(t)
    assert t["range_edges_m"] == [0.0, 1.0, 100.0]
    assert t["gain"] == pytest.approx([0.62, 0.64], abs=0.01)
    assert t["bearing_leak"] == pytest.approx([-0.16, -0.07], abs=0.01)
    assert [b["probed_at_m"] for b in out["bins"]] == [[0.5, 0.75], [3.0, 4.0]]
    assert [b["frames"] for b in out["bins"]] == [144, 144]
    with pytest.raises(HeadCropGainError, match="1-100 m: 0 frames"):
        gain_table(_rows({0.5: (0.62, -0.16)}), (0.0, 1.0, 100.0), min_frames=50)
    with pytest.raises(HeadCropGainError, match=r"0-1 m: gain 0\.\d+ outside 0.4-2.0"):
        gain_table(_rows({0.5: (0.3, 0.0)}), (0.0, 1.0), min_frames=50)
    with pytest.raises(HeadCropGainError, match=r"bearing leak -0\.\d+ outside -0.5-0.5"):
        gain_table(_rows({0.5: (0.9, -0.7)}), (0.0, 1.0), min_frames=50)


def test_each_bin_is_probed_at_its_near_edge_and_its_middle():
    assert bin_ranges_m((0.0, 1.0, 1.5, 2.0, 3.0, 5.0, 8.0, 100.0)) == [
        (0.5, 0.75),
        (1.0, 1.25),
        (1.5, 1.75),
        (2.0, 2.5),
        (3.0, 4.0),
        (5.0, 6.5),
        (8.0, 10.0),
    ]


@pytest.mark.parametrize(
    "argv, match",
    [
        (["--spec", "models/scenes/train.json", "--scenes", "tr001,nope"], "nope"),
        (["--spec", "/no/such/set.json"], "cannot read the scene spec"),
        (
            ["--spec", "models/scenes/train.json", "--scenes", "tr001", "--model", "/no/model.onnx"],
            "not found",
        ),
        (["--spec", "models/scenes/train.json", "--min-frames", "1"], "--min-frames"),
        (["--spec", "models/scenes/train.json", "--range-edges", "3,1"], "--range-edges"),
    ],
)
def test_bad_input_is_refused_before_anything_is_rendered(argv, match, tmp_path, capsys):
    out = tmp_path / "g.json"
    assert main([*argv, "--out", str(out), "--no-progress"]) == 2
    assert match in capsys.readouterr().err
    assert not out.exists()


def test_a_real_network_is_measured_on_rendered_probe_frames(tmp_path):
    """The shipped network on one training scene, one bin probed at 0.5 and 6.25 m: gain and leak
    inside the flight code's limits, the file the export reads."""
    from oibar_models.kp_export import load_head_crop_gain

    out = tmp_path / "g.json"
    rc = main(
        ["--spec", "models/scenes/train.json", "--scenes", "tr001", "--range-edges", "0,100"]
        + ["--min-frames", "16", "--out", str(out), "--plot", str(tmp_path / "g.png"), "--no-progress"]
    )
    assert rc == 0
    doc = json.loads(out.read_text())
    assert doc["ranges_m"] == [0.5, 6.25] and doc["frames"] == 36 and doc["scenes"] == ["tr001"]
    table = load_head_crop_gain(out)
    assert 0.4 <= table["gain"][0] <= 2.0 and -0.5 <= table["bearing_leak"][0] <= 0.5
    assert (tmp_path / "g.png").stat().st_size > 1000
