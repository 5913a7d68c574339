"""The committed scene sets: make_scenes.py writes exactly the committed files, and its Sun fill
keeps every training run clear of the test and validation scenes it must not resemble."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[2]
SCENES = REPO / "models/scenes"


@pytest.fixture(scope="module")
def make_scenes():
    spec = importlib.util.spec_from_file_location("make_scenes", SCENES / "make_scenes.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_the_committed_scene_sets_are_what_make_scenes_writes(make_scenes, tmp_path, monkeypatch):
    """A set edited by hand, or a draw moved in the script, would change scenes that models were
    trained and judged on: the script must write every committed file byte for byte."""
    monkeypatch.setattr(make_scenes, "HERE", tmp_path)
    make_scenes.main()
    written = sorted(p.name for p in tmp_path.glob("*.json"))
    assert written == sorted(p.name for p in SCENES.glob("*.json"))
    for name in written:
        assert (tmp_path / name).read_text() == (SCENES / name).read_text(), name


def test_the_sun_fill_covers_each_allowed_stretch_and_keeps_its_margin(make_scenes):
    """One cell with a test scene at 60 deg and a validation scene at 120: the fill puts runs at
    both ends of each allowed stretch (the margin plus 0.5 deg from those scenes), no two more
    than 12 deg apart inside a stretch, none closer than the margin, none within 4 deg of a
    training run (which covers its Sun)."""
    m = make_scenes.SUN_MARGIN_DEG + 0.5
    keep = [(3, "iss", 60.0), (3, "iss", 120.0), (5, "perlin", 90.0)]
    have = [(3, "iss", 86.0)]
    out = make_scenes.sun_fill("tr", 7, 500, np.random.default_rng(1), keep, have)
    cell = sorted(s["sun_elevation_deg"] for s in out if (s["port"], s["background"]) == (3, "iss"))
    lo, hi = make_scenes.SUN_RANGE_DEG
    for stretch in ((lo, 60.0 - m), (60.0 + m, 120.0 - m), (120.0 + m, hi)):
        inside = [s for s in cell if stretch[0] <= s <= stretch[1]]
        ends = [stretch[0], stretch[1]]
        assert [e for e in ends if abs(e - 86.0) >= 4.0] == [e for e in ends if e in inside]
        covered = sorted(inside + [86.0] * (stretch[0] <= 86.0 <= stretch[1]))
        assert np.all(np.diff(covered) <= 12.0 + 1e-9), covered
    assert all(min(abs(s - 60.0), abs(s - 120.0)) >= m - 1e-9 for s in cell)
    assert all(abs(s - 86.0) >= 4.0 for s in cell) and len(cell) < len(out)
    assert len(cell) == len(set(cell))
    # every other cell is filled too, names and seeds run on from the ones given
    assert {(s["port"], s["background"]) for s in out} == {
        (p, b) for p in range(1, 7) for b in ("iss", "perlin")
    }
    assert [s["name"] for s in out] == [f"tr{7 + i:03d}" for i in range(len(out))]
    assert [s["seed"] for s in out] == list(range(500, 500 + len(out)))


def test_the_sun_filled_set_holds_the_turned_set_first(make_scenes):
    """Models trained on train_turned.json can be fine-tuned on the filled set without renaming a
    scene: its first scenes are train_turned.json's, unchanged."""
    turned = json.loads((SCENES / "train_turned.json").read_text())["scenes"]
    filled = json.loads((SCENES / "train_sunfill.json").read_text())["scenes"]
    assert filled[: len(turned)] == turned and len(filled) > len(turned)


def test_the_turned_near_axis_set_is_the_near_axis_set_without_the_sun_fill():
    """Stage 22 asks whether the Sun-filled runs are what shortened the 3 m view: its set must be
    train_turned.json's scenes plus the very near-axis runs stage 21 saw (same names, seeds and
    Suns), and none of the Sun-filled runs."""
    turned, filled, near, ours = (
        json.loads((SCENES / f"{n}.json").read_text())["scenes"]
        for n in ("train_turned", "train_sunfill", "train_nearaxis", "train_turned_nearaxis")
    )
    added = near[len(filled) :]
    assert len(added) == 24 and all(0.06 <= s["offaxis_m"] <= 0.15 for s in added)
    assert ours == turned + added
    names = {s["name"] for s in ours}
    assert not names & {s["name"] for s in filled[len(turned) :]}


def test_the_wandering_sun_fill_keeps_each_look_and_changes_only_the_view():
    """Stage 23 asks whether the Sun-filled runs shortened the 3 m view by their aligned approach:
    its set must be stage 22's plus the same 80 looks (port, background, Sun, kind), each under a
    new name and seed, every other one off the axis and every other one of those turned, so the
    aligned share is stage 15's again (88 of 224 against 48 of 120), and nothing else."""
    filled, turned, ours22, ours = (
        json.loads((SCENES / f"{n}.json").read_text())["scenes"]
        for n in ("train_sunfill", "train_turned", "train_turned_nearaxis", "train_sunwander")
    )
    looks = filled[len(turned) :]
    added = ours[len(ours22) :]
    assert ours[: len(ours22)] == ours22 and len(added) == len(looks) == 80
    view = {"name", "seed", "offaxis_m", "turned_deg"}
    for j, (a, look) in enumerate(zip(added, looks, strict=True)):
        assert {k: v for k, v in a.items() if k not in view} == {
            k: v for k, v in look.items() if k not in view
        }
        assert ("offaxis_m" in a) == bool(j % 2) and 0.2 <= a.get("offaxis_m", 0.2) <= 0.9
        assert ("turned_deg" in a) == (j % 4 == 3) and 1.5 <= a.get("turned_deg", 1.5) <= 6.0

    def aligned(scenes):
        return sum(1 for s in scenes if not s.get("offaxis_m") and not s.get("turned_deg"))

    assert (aligned(turned), len(turned)) == (48, 120) and (aligned(ours), len(ours)) == (88, 224)
    names = [s["name"] for s in ours]
    assert len(set(names)) == len(names)
    seeds = [s["seed"] for s in ours]
    assert len(set(seeds)) == len(seeds)
    near = json.loads((SCENES / "train_nearaxis.json").read_text())["scenes"]
    assert not {s["name"] for s in added} & {s["name"] for s in near}
