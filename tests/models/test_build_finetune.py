"""A candidate fine-tuned from a flight file, rebuilt from its recipe (stage kinds finetune,
head_gain, retag: oibar_models.build_finetune): bad stages are refused naming the key; the
committed candidate recipe (models/recipes/oibarnet_kp_ft.toml) loads and plans its training
sequences in order; its smoke recipe (oibarnet_kp_ft_smoke.toml, the same chain at toy size)
fine-tunes the shipped file, measures the head's gain, chooses the fusion with it, retags and
evaluates, logs to MLflow, and skips every stage on a rerun.

Cost: one smoke build and two reruns, about a minute on 2 shared CPU cores."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import pytest

from oibar.hashing import sha256_file
from oibar_models.build import MARKER, Build, BuildError, main
from oibar_models.recipe import RecipeError, load_recipe

REPO = Path(__file__).resolve().parents[2]
FT = REPO / "models/recipes/oibarnet_kp_ft.toml"
FT_SMOKE = REPO / "models/recipes/oibarnet_kp_ft_smoke.toml"
TRAIN_STAGE = """[[stages]]
name = "stage1"
kind = "train"
config = "models/configs/keypoints/oibarnet_kp.yaml"
init = "imagenet"
train_data = "train_base"
val_data = "val"

[[stages]]
name = "finetune"
"""


def test_the_candidate_recipe_starts_from_0_34_0s_file_with_0_35_1s_chain_and_the_turned_runs():
    r = load_recipe(FT)
    assert (r.name, r.model_version, r.seed, r.threads) == ("oibarnet_kp_ft", "0.35.3", 0, 2)
    assert [(s.name, s.kind) for s in r.stages] == [
        ("finetune", "finetune"),
        ("head_gain", "head_gain"),
        ("fusion", "fusion"),
        ("retag", "retag"),
        ("evaluate", "evaluate"),
    ]  # no card: a candidate is not registered
    ds = r.datasets
    assert ds["train_base"].scenes == [f"tr{i:03d}" for i in range(0, 96, 4)]
    assert ds["train_turned"].scenes == [f"tr{i:03d}" for i in [*range(96, 120), *range(200, 224)]]
    assert ds["train_turned"].spec == "models/scenes/train_turned_nearaxis.json"
    assert (
        ds["train_dr"].scenes == [f"dr{i:03d}" for i in range(0, 288, 6)]
        and ds["train_dr"].root == "data/train_dr"
    )
    assert ds["val"].spec == "models/scenes/val.json" and ds["val"].scenes == []
    assert all(d.root for d in ds.values()) and all(d.frames_limit == 0 for d in ds.values())
    ft = r.stage("finetune").opts
    # 0.34.0, kept beside its registry entry since 0.35.15 shipped
    assert ft["init"] == "models/registry/oibarnet-0.34.0/oibarnet.onnx"
    assert ft["init_sha256"] == sha256_file(REPO / ft["init"])
    assert ft["train_data"] == ["train_base", "train_turned", "train_dr"] and ft["val_data"] == "val"
    assert (ft["steps"], ft["lr"], ft["batch_size"], ft["batch_norm"], ft["far_network"]) == (
        1000,
        2e-4,
        16,
        "frozen",
        False,
    )
    assert (
        r.stage("head_gain")["stride"] == 4 and r.stage("head_gain")["min_frames"] == 0
    )  # kp_head_gain's own
    fu = r.stage("fusion").opts
    assert (fu["priors"], fu["pairs"], fu["stride"], fu["head_gain"]) == (["head"], [[2, 3]], 4, "head_gain")
    # 0.35.3: the keypoints alone from 3 to 5 m (the probe's 3 m answer slopes)
    assert fu["prior_sigma_scale"] == {
        "range_edges_m": [0.0, 3.0, 5.0, 100.0],
        "sigma_scale": [1.0, 1000.0, 1.0],
    }
    rt = r.stage("retag").opts
    assert (rt["fusion"], rt["head_gain"], rt["finder"]) == ("fusion", "head_gain", "")
    ev = r.stage("evaluate").opts
    assert (ev["model"], ev["stride"], ev["modes"]) == ("retag", 2, ["track"])


def test_the_no_turned_runs_candidate_is_the_candidate_recipe_without_them():
    """models/recipes/oibarnet_kp_ft_noturned.toml (0.35.5) is oibarnet_kp_ft.toml with the turned
    and near-axis runs taken out of the data and the fine-tune, and nothing else changed: the
    stages, their options and every other dataset are the same."""
    a, b = load_recipe(FT), load_recipe(REPO / "models/recipes/oibarnet_kp_ft_noturned.toml")
    assert (b.name, b.model_version) == ("oibarnet_kp_ft_noturned", "0.35.5")
    assert list(b.datasets) == [k for k in a.datasets if k != "train_turned"]
    assert all(b.datasets[k] == a.datasets[k] for k in b.datasets)
    assert [(s.name, s.kind) for s in b.stages] == [(s.name, s.kind) for s in a.stages]
    for sa, sb in zip(a.stages, b.stages, strict=True):
        want = dict(sa.opts)
        if sa.kind == "finetune":
            want["train_data"] = [d for d in want["train_data"] if d != "train_turned"]
        assert sb.opts == want, sa.name
    assert b.stage("fusion").opts["prior_sigma_scale"]["sigma_scale"] == [1.0, 1000.0, 1.0]


def _noturned_but(name: str, version: str, edits: dict[str, dict]) -> None:
    """models/recipes/<name>.toml is oibarnet_kp_ft_noturned.toml (0.35.5) with the options in
    `edits` (by stage kind) changed, its own name and version, and nothing else changed."""
    a = load_recipe(REPO / "models/recipes/oibarnet_kp_ft_noturned.toml")
    b = load_recipe(REPO / f"models/recipes/{name}.toml")
    assert (b.name, b.model_version) == (name, version)
    assert b.datasets == a.datasets
    assert [(s.name, s.kind) for s in b.stages] == [(s.name, s.kind) for s in a.stages]
    for sa, sb in zip(a.stages, b.stages, strict=True):
        want = dict(sa.opts)
        assert all(sa.opts[k] != v for k, v in edits.get(sa.kind, {}).items()), sa.name  # each a change
        assert sb.opts == want | edits.get(sa.kind, {}), sa.name


def test_the_head_frozen_candidate_is_the_no_turned_runs_candidate_with_its_attitude_head_kept():
    """0.35.6: `freeze = ["attitude"]` in the fine-tune."""
    _noturned_but("oibarnet_kp_ft_headfrozen", "0.35.6", {"finetune": {"freeze": ["attitude"]}})


def test_the_backbone_frozen_candidate_is_the_no_turned_runs_candidate_with_0_34_0s_features_and_no_scale():
    """0.35.7: the backbone and the attitude head frozen in the fine-tune, and the fusion without
    the prior's scale (a frozen backbone reads as 0.34.0's, whose head needed none)."""
    _noturned_but(
        "oibarnet_kp_ft_bbfrozen",
        "0.35.7",
        {"finetune": {"freeze": ["backbone", "attitude"]}, "fusion": {"prior_sigma_scale": {}}},
    )


def test_the_distilled_candidate_is_the_head_frozen_one_distilled_fused_with_the_head_and_with_a_finder():
    """0.35.8: 0.35.6's recipe (0.35.5 with the head frozen) with the attitude head's answers on the
    base renderer's crops distilled, a fusion that must carry the head prior and no prior scale,
    and the fixture finder trained on 0.1.0's half of the base scenes and the randomised looks."""
    a = load_recipe(REPO / "models/recipes/oibarnet_kp_ft_headfrozen.toml")
    b = load_recipe(REPO / "models/recipes/oibarnet_kp_ft_distill.toml")
    assert (b.name, b.model_version) == ("oibarnet_kp_ft_distill", "0.35.8")
    assert {k: v for k, v in b.datasets.items() if k != "train_half"} == a.datasets
    half = b.datasets["train_half"]
    assert (half.spec, half.root) == (a.datasets["train_base"].spec, a.datasets["train_base"].root)
    assert half.scenes == [f"tr{i:03d}" for i in range(0, 96, 2)]  # as make dataset-train SHARD=0/2
    assert set(a.datasets["train_base"].scenes) < set(half.scenes)
    edits = {
        "finetune": {"distill_weight": 1.0, "distill_data": ["train_base"]},
        "fusion": {"pnp_alone": False, "prior_sigma_scale": {}},
        "retag": {"finder": "finder"},
    }
    assert [s.name for s in b.stages] == ["finetune", "head_gain", "fusion", "finder", "retag", "evaluate"]
    for sa in a.stages:
        sb = b.stage(sa.name)
        assert sb.kind == sa.kind
        assert all(sa.opts[k] != v for k, v in edits.get(sa.kind, {}).items()), sa.name  # each a change
        assert sb.opts == sa.opts | edits.get(sa.kind, {}), sa.name
    f = b.stage("finder").opts
    assert (f["keypoints_from"], f["train_data"], f["val_data"]) == (
        "finetune",
        ["train_half", "train_dr"],
        "val",
    )
    from oibar_models.finetune import DISTILL_WEIGHT

    assert b.stage("finetune").opts["distill_weight"] == DISTILL_WEIGHT


def test_the_refit_candidate_is_the_head_frozen_fine_tune_then_its_head_alone_taught_by_0_34_0():
    """0.35.9: 0.35.6's fine-tune as it is, then a second fine-tune from its file in which only the
    attitude head trains, held to the shipped 0.34.0's answers on the base renderer's crops; the
    rest is 0.35.8's chain (head gain, a fusion that must carry the head prior, the finder, retag,
    evaluate), read from the refitted file."""
    a = load_recipe(REPO / "models/recipes/oibarnet_kp_ft_headfrozen.toml")
    d = load_recipe(REPO / "models/recipes/oibarnet_kp_ft_distill.toml")
    b = load_recipe(REPO / "models/recipes/oibarnet_kp_ft_refit.toml")
    assert (b.name, b.model_version) == ("oibarnet_kp_ft_refit", "0.35.9")
    assert b.datasets == d.datasets
    assert [s.name for s in b.stages] == ["finetune", "refit", *[s.name for s in d.stages[1:]]]
    assert b.stage("finetune").opts == a.stage("finetune").opts
    first = a.stage("finetune").opts
    refit = {
        "init": "finetune",
        "init_sha256": "",
        "freeze": ["backbone", "lateral", "head", "present"],
        "distill_weight": 1.0,
        "distill_data": ["train_base"],
        "distill_from": "models/registry/oibarnet-0.34.0/oibarnet.onnx",
        "distill_from_sha256": first["init_sha256"],  # the teacher is the file the first stage starts from
    }
    assert b.stage("refit").opts == first | refit
    from oibar_models.finetune import DISTILL_WEIGHT, FREEZABLE

    assert set(FREEZABLE) - set(refit["freeze"]) == {"attitude"} and refit["distill_weight"] == DISTILL_WEIGHT
    for sd in d.stages[1:]:
        sb = b.stage(sd.name)
        moved = {k: "refit" for k in ("model", "keypoints_from") if sd.opts.get(k) == "finetune"}
        assert sb.kind == sd.kind and sb.opts == sd.opts | moved, sd.name


def test_the_last_map_candidate_is_the_distilled_one_holding_the_backbones_map_instead():
    """0.35.10 is 0.35.8's recipe but for what its fine-tune holds: the backbone's stride-32 map,
    10 per unit of relative squared difference, on the same crops, from the same teacher."""
    d = load_recipe(REPO / "models/recipes/oibarnet_kp_ft_distill.toml")
    c = load_recipe(REPO / "models/recipes/oibarnet_kp_ft_lasttap.toml")
    assert (c.name, c.model_version) == ("oibarnet_kp_ft_lasttap", "0.35.10")
    assert c.datasets == d.datasets and [s.name for s in c.stages] == [s.name for s in d.stages]
    held = {"distill_weight": 10.0, "distill_target": "last_tap"}
    assert d.stage("finetune").opts["distill_target"] == "attitude"
    assert c.stage("finetune").opts == d.stage("finetune").opts | held
    assert c.stage("finetune").opts["freeze"] == ["attitude"]  # 0.34.0's head reads the held map
    for sd in d.stages[1:]:
        assert c.stage(sd.name).kind == sd.kind and c.stage(sd.name).opts == sd.opts, sd.name


def test_the_mixed_randomised_candidate_is_0_35_6_with_every_port_and_kind_of_approach():
    """0.35.11 is 0.35.6's recipe but for its randomised scenes, which 0.35.6 drew all from port 1
    and all plain (every 6th of a set that cycles port and kind with the index), and a finder
    stage as 0.35.8's; its 48 span every port equally and each kind in the whole set's share."""
    from collections import Counter

    a = load_recipe(REPO / "models/recipes/oibarnet_kp_ft_headfrozen.toml")
    d = load_recipe(REPO / "models/recipes/oibarnet_kp_ft_distill.toml")
    m = load_recipe(REPO / "models/recipes/oibarnet_kp_ft_drmix.toml")
    assert (m.name, m.model_version) == ("oibarnet_kp_ft_drmix", "0.35.11")
    dr = json.loads((REPO / "models/scenes/train_dr.json").read_text())["scenes"]
    by_name = {s["name"]: s for s in dr}

    def kinds(names):
        scenes = [by_name[n] for n in names]
        return Counter(s["port"] for s in scenes), {
            k: sum(k in s for s in scenes) for k in ("turned_deg", "offaxis_m", "rolled_deg")
        }

    ports, kind = kinds(a.datasets["train_dr"].scenes)
    assert ports == {1: 48} and kind == {"turned_deg": 0, "offaxis_m": 0, "rolled_deg": 0}  # 0.35.6's
    names = m.datasets["train_dr"].scenes
    assert names == [f"dr{6 * k + (k % 12) // 2:03d}" for k in range(48)]
    ports, kind = kinds(names)
    whole = {k: sum(k in s for s in dr) / len(dr) for k in kind}
    assert ports == {p: 8 for p in range(1, 7)}
    assert {k: v / 48 for k, v in kind.items()} == whole  # 1/4 turned, 1/2 off-axis, 1/3 rolled
    assert m.datasets["train_base"] == a.datasets["train_base"] and m.datasets["val"] == a.datasets["val"]
    assert m.datasets["train_half"] == d.datasets["train_half"]
    assert [s.name for s in m.stages] == ["finetune", "head_gain", "fusion", "finder", "retag", "evaluate"]
    for sa in a.stages:
        extra = {"finder": "finder"} if sa.kind == "retag" else {}
        assert m.stage(sa.name).opts == sa.opts | extra, sa.name
    assert m.stage("finder").opts == d.stage("finder").opts


def test_the_head_reading_candidate_is_0_35_7_with_its_fusion_made_to_read_the_head():
    """0.35.12 is 0.35.7's recipe (0.34.0's backbone and attitude head kept) but for a fusion that
    may not choose PnP alone and a finder stage as 0.35.8's."""
    f = load_recipe(REPO / "models/recipes/oibarnet_kp_ft_bbfrozen.toml")
    d = load_recipe(REPO / "models/recipes/oibarnet_kp_ft_distill.toml")
    h = load_recipe(REPO / "models/recipes/oibarnet_kp_ft_bbhead.toml")
    assert (h.name, h.model_version) == ("oibarnet_kp_ft_bbhead", "0.35.12")
    assert h.datasets == f.datasets | {"train_half": d.datasets["train_half"]}
    assert [s.name for s in h.stages] == ["finetune", "head_gain", "fusion", "finder", "retag", "evaluate"]
    edits = {"fusion": {"pnp_alone": False}, "retag": {"finder": "finder"}}
    for sf in f.stages:
        assert all(sf.opts[k] != v for k, v in edits.get(sf.name, {}).items()), sf.name  # each a change
        assert h.stage(sf.name).opts == sf.opts | edits.get(sf.name, {}), sf.name
    assert h.stage("finetune").opts["freeze"] == ["backbone", "attitude"]
    assert h.stage("finder").opts == d.stage("finder").opts


def test_the_crop_gain_candidate_is_0_35_6s_fine_tune_read_through_its_heads_crop_gain():
    """0.35.13 is 0.35.6's recipe (its datasets, its fine-tune as it is) with the docking-frame
    head gain replaced by the crop gain, measured on the odd training scenes every 4th from tr001
    (none of them trained on), the head prior carried at every range (no scale, no PnP alone),
    and a finder stage as 0.35.8's."""
    h = load_recipe(REPO / "models/recipes/oibarnet_kp_ft_headfrozen.toml")
    d = load_recipe(REPO / "models/recipes/oibarnet_kp_ft_distill.toml")
    c = load_recipe(REPO / "models/recipes/oibarnet_kp_ft_cropgain.toml")
    assert (c.name, c.model_version) == ("oibarnet_kp_ft_cropgain", "0.35.13")
    assert c.datasets == h.datasets | {"train_half": d.datasets["train_half"]}
    assert [s.name for s in c.stages] == [
        "finetune",
        "head_crop_gain",
        "fusion",
        "finder",
        "retag",
        "evaluate",
    ]
    assert c.stage("finetune").opts == h.stage("finetune").opts
    cg = c.stage("head_crop_gain").opts
    assert cg["model"] == "finetune" and cg["spec"] == "models/scenes/train.json"
    assert cg["scenes"] == [f"tr{i:03d}" for i in range(1, 96, 4)]
    assert not set(cg["scenes"]) & set(c.datasets["train_base"].scenes)
    assert (cg["min_frames"], cg["range_edges_m"]) == (0, [])  # the measurement's own
    fh = dict(h.stage("fusion").opts)
    assert fh.pop("head_gain") == "head_gain" and fh.pop("prior_sigma_scale")
    edits = {"head_crop_gain": "head_crop_gain", "pnp_alone": False, "head_gain": "", "prior_sigma_scale": {}}
    assert c.stage("fusion").opts == fh | edits
    assert c.stage("finder").opts == d.stage("finder").opts
    rt = c.stage("retag").opts
    assert (rt["fusion"], rt["head_gain"], rt["head_crop_gain"], rt["finder"]) == (
        "fusion",
        "",
        "head_crop_gain",
        "finder",
    )
    assert c.stage("evaluate").opts == h.stage("evaluate").opts


def test_the_used_head_error_candidate_is_0_35_13_with_the_heads_error_measured_as_corrected():
    """0.35.14 is 0.35.13's recipe, stage for stage, but for its fusion's head error model,
    measured on the head as the fit uses it (head_error = "as_used")."""
    c = load_recipe(REPO / "models/recipes/oibarnet_kp_ft_cropgain.toml")
    u = load_recipe(REPO / "models/recipes/oibarnet_kp_ft_cropgain_used.toml")
    assert (u.name, u.model_version) == ("oibarnet_kp_ft_cropgain_used", "0.35.14")
    assert u.datasets == c.datasets and [s.name for s in u.stages] == [s.name for s in c.stages]
    assert c.stage("fusion").opts["head_error"] == "as_read"
    for sc in c.stages:
        edits = {"head_error": "as_used"} if sc.name == "fusion" else {}
        assert u.stage(sc.name).opts == sc.opts | edits, sc.name


def test_the_five_degree_candidate_is_0_35_14_with_the_head_prior_at_5_deg():
    """0.35.15 is 0.35.14's recipe, stage for stage, but for its fusion's one pair of weights:
    2 crop px : 5 deg instead of 2 : 3."""
    a = load_recipe(REPO / "models/recipes/oibarnet_kp_ft_cropgain_used.toml")
    b = load_recipe(REPO / "models/recipes/oibarnet_kp_ft_cropgain_used5.toml")
    assert (b.name, b.model_version) == ("oibarnet_kp_ft_cropgain_used5", "0.35.15")
    assert b.datasets == a.datasets and [s.name for s in b.stages] == [s.name for s in a.stages]
    for sa in a.stages:
        edits = {"pairs": [[2, 5]]} if sa.name == "fusion" else {}
        assert b.stage(sa.name).opts == sa.opts | edits, sa.name
    assert b.stage("fusion").opts["head_error"] == "as_used"


def test_the_rolled_candidate_is_0_35_15_with_a_quarter_of_its_crops_turned_and_its_finder():
    """0.35.16 is 0.35.15's recipe, stage for stage, but for its fine-tune's rolled crops
    (roll_share 0.25), its retag saying so (keypoints_any_turn), and its finder: 0.35.15's file,
    not a stage that would retrain it unchanged (so neither the finder stage nor the half
    training set it read). 0.35.17 is 0.35.16 trained three times as long, 0.35.18 is
    0.35.17 with a tenth of its crops turned."""
    a = load_recipe(REPO / "models/recipes/oibarnet_kp_ft_cropgain_used5.toml")
    b = load_recipe(REPO / "models/recipes/oibarnet_kp_ft_rolled.toml")
    assert (b.name, b.model_version) == ("oibarnet_kp_ft_rolled", "0.35.16")
    assert b.datasets == {k: v for k, v in a.datasets.items() if k != "train_half"}
    assert [s.name for s in b.stages] == [s.name for s in a.stages if s.name != "finder"]
    assert a.stage("finetune").opts["roll_share"] == 0.0
    for sb in b.stages:
        edits = {
            "finetune": {"roll_share": 0.25},
            "retag": {"finder": "models/oibarnet_finder.onnx", "keypoints_any_turn": True},
        }.get(sb.name, {})
        assert sb.opts == a.stage(sb.name).opts | edits, sb.name
    c = load_recipe(REPO / "models/recipes/oibarnet_kp_ft_rolled3k.toml")
    assert (c.name, c.model_version) == ("oibarnet_kp_ft_rolled3k", "0.35.17") and c.datasets == b.datasets
    for sc in c.stages:
        edits = {"steps": 3000} if sc.name == "finetune" else {}
        assert sc.opts == b.stage(sc.name).opts | edits, sc.name
    d = load_recipe(REPO / "models/recipes/oibarnet_kp_ft_rolled3k10.toml")  # and 0.35.18, a tenth turned
    assert (d.name, d.model_version) == ("oibarnet_kp_ft_rolled3k10", "0.35.18") and d.datasets == c.datasets
    for sd in d.stages:
        edits = {"roll_share": 0.1} if sd.name == "finetune" else {}
        assert sd.opts == c.stage(sd.name).opts | edits, sd.name


def test_the_continued_rolled_candidate_starts_from_the_shipped_0_35_15():
    """0.35.19 is 0.35.18 fine-tuned from 0.35.15's file (pinned by the sha256 the registry keeps
    for it) instead of 0.34.0's: 2000 steps at half the learning rate, the rest as 0.35.18; 0.35.20
    is 0.35.19 trained twice as long, and 0.35.21 twice as long again."""
    import tomllib

    d = load_recipe(REPO / "models/recipes/oibarnet_kp_ft_rolled3k10.toml")
    e = load_recipe(REPO / "models/recipes/oibarnet_kp_ft_rolled_cont.toml")
    assert (e.name, e.model_version) == ("oibarnet_kp_ft_rolled_cont", "0.35.19") and e.datasets == d.datasets
    registry = tomllib.loads((REPO / "models/registry.toml").read_text())
    (shipped,) = [m for m in registry["models"] if (m["name"], m["version"]) == ("oibarnet", "0.35.15")]
    edits = {
        "init": "models/oibarnet.onnx",
        "init_sha256": shipped["files"]["models/oibarnet.onnx"],
        "steps": 2000,
        "lr": 1e-4,
    }
    for se in e.stages:
        assert se.opts == d.stage(se.name).opts | (edits if se.name == "finetune" else {}), se.name
    # 0.35.20 twice as long, 0.35.21 twice again: only the steps differ from 0.35.19
    for name, version, steps in (("cont4k", "0.35.20", 4000), ("cont8k", "0.35.21", 8000)):
        g = load_recipe(REPO / f"models/recipes/oibarnet_kp_ft_rolled_{name}.toml")
        assert (g.name, g.model_version) == (f"oibarnet_kp_ft_rolled_{name}", version)
        assert g.datasets == e.datasets
        for sg in g.stages:
            edits = {"steps": steps} if sg.name == "finetune" else {}
            assert sg.opts == e.stage(sg.name).opts | edits, sg.name


def test_the_candidate_recipe_plans_its_training_sequences_in_order(tmp_path):
    """Without rendering or training anything: the fine-tune's sequences are its datasets in the
    order listed, each dataset's scenes in its own order, in the standard render folders."""
    from oibar_models.build_finetune import sequences

    b = Build(load_recipe(FT), tmp_path, progress=False)
    assert b.plan() == {}  # no train stage; the scene lists are written
    train, held = sequences(b, b.recipe.stage("finetune"))
    assert len(train) == 120 and len(held) == 22
    assert [p.name for p in train[:2]] == ["tr000", "tr004"] and train[0].parent == REPO / "data/train"
    assert [p.name for p in train[24:26]] == ["tr096", "tr097"] and train[24].parent == REPO / "data/train"
    assert (
        train[72].name == "dr000" and train[72].parent == REPO / "data/train_dr" and train[-1].name == "dr282"
    )
    assert held[0] == REPO / "data/val/va000"
    scene_list = json.loads((tmp_path / "oibarnet_kp_ft/data/train_dr.json").read_text())
    assert len(scene_list["scenes"]) == 48
    assert not (tmp_path / "oibarnet_kp_ft/finetune").exists()  # nothing ran


def test_an_init_that_is_not_the_pinned_file_is_refused_before_anything_runs(tmp_path):
    recipe = load_recipe(FT_SMOKE)
    st = recipe.stage("finetune")
    pinned = dataclasses.replace(st, opts={**st.opts, "init_sha256": "0" * 64})
    b = Build(dataclasses.replace(recipe, stages=[pinned]), tmp_path, progress=False)
    with pytest.raises(BuildError, match="the recipe pins 000000000000"):
        b.finetune(pinned)
    assert not (tmp_path / recipe.name / "finetune").exists()
    # and a teacher that is not the pinned file
    teacher = {"distill_from": "models/oibarnet.onnx", "distill_from_sha256": "1" * 64}
    pinned = dataclasses.replace(st, opts={**st.opts, **teacher})
    b = Build(dataclasses.replace(recipe, stages=[pinned]), tmp_path, progress=False)
    with pytest.raises(BuildError, match="the recipe pins 111111111111"):
        b.finetune(pinned)
    assert not (tmp_path / recipe.name / "finetune").exists()


def test_the_batch_norm_choices_are_the_fine_tunes():
    from oibar_models.finetune import BATCH_NORM, LR, STEPS
    from oibar_models.recipe import BATCH_NORM as RECIPE_BATCH_NORM
    from oibar_models.recipe import STAGE_KEYS

    assert RECIPE_BATCH_NORM == BATCH_NORM
    from oibar_models.finetune import FREEZABLE
    from oibar_models.recipe import FREEZABLE as RECIPE_FREEZABLE

    assert RECIPE_FREEZABLE == FREEZABLE
    from oibar_models.finetune import DISTILL_TARGETS
    from oibar_models.recipe import DISTILL_TARGETS as RECIPE_DISTILL_TARGETS

    assert RECIPE_DISTILL_TARGETS == DISTILL_TARGETS
    assert STAGE_KEYS["finetune"]["steps"][1] == STEPS and STAGE_KEYS["finetune"]["lr"][1] == LR


@pytest.mark.parametrize(
    "edit, match",
    [
        (
            ('train_data = ["train_base", "train_dr"]', 'train_data = "train_base"'),
            "finetune' train_data: expected list",
        ),
        (
            ('train_data = ["train_base", "train_dr"]', "train_data = []"),
            "a list of one or more dataset names",
        ),
        (('train_data = ["train_base", "train_dr"]', 'train_data = ["train_base", 3]'), "dataset names"),
        (
            ('train_data = ["train_base", "train_dr"]', 'train_data = ["train_base", "lab"]'),
            "no dataset 'lab'",
        ),
        (('train_data = ["train_base", "train_dr"]', 'train_data = ["train_dr", "train_dr"]'), "named twice"),
        (
            ('train_data = ["train_base", "train_dr"]', 'train_data = ["train_base", "val"]'),
            "is also trained on",
        ),
        (('batch_norm = "frozen"', 'batch_norm = "thawed"'), "batch_norm: one of"),
        (("far_network = false", "far_network = 0"), "far_network: expected bool"),
        (('freeze = ["attitude"]', 'freeze = ["attitudes"]'), "freeze: distinct parts of"),
        (('freeze = ["attitude"]', 'freeze = ["attitude", "attitude"]'), "freeze: distinct parts of"),
        (('freeze = ["attitude"]', 'freeze = "attitude"'), "freeze: expected list"),
        (
            ('freeze = ["attitude"]', 'freeze = ["backbone", "lateral", "head", "present", "attitude"]'),
            "leaves nothing to train",
        ),
        (("distill_weight = 1.0", "distill_weight = -1.0"), "distill_weight: a finite number >= 0"),
        (("distill_weight = 1.0", "distill_weight = nan"), "distill_weight: a finite number >= 0"),
        (("distill_weight = 1.0", "distill_weight = 0.0"), "distill_data: given with no distill_weight"),
        (
            ('distill_weight = 1.0\ndistill_data = ["train_base"]\ndistill_from', "distill_from"),
            "distill_from: given with no distill_weight",
        ),
        (('distill_data = ["train_base"]', 'distill_data = ["val"]'), "distill_data: distinct datasets of"),
        (
            ('distill_data = ["train_base"]', 'distill_data = ["train_base"]\ndistill_target = "features"'),
            "distill_target: one of",
        ),
        (
            (
                "distill_weight = 1.0  # as the distilled candidate (oibarnet_kp_ft_distill.toml)\n"
                'distill_data = ["train_base"]',
                'distill_target = "last_tap"',
            ),
            "distill_target: given with no distill_weight",
        ),
        (
            ('distill_data = ["train_base"]', 'distill_data = ["train_base", "train_base"]'),
            "distill_data: distinct datasets of",
        ),
        (('freeze = ["attitude"]', 'freeze = ["attitude"]\nroll_share = 1.5'), "roll_share: a share in"),
        (('freeze = ["attitude"]', 'freeze = ["attitude"]\nroll_share = nan'), "roll_share: a share in"),
        (("pnp_alone = false", "pnp_alone = 0"), "pnp_alone: expected bool"),
        (
            ('head_error = "as_used"', 'head_error = "as_fitted"'),
            "head_error: one of as_read, as_used, got 'as_fitted'",
        ),
        (("steps = 2", "steps = 0"), "steps, batch_size: must be >= 1"),
        (("lr = 2e-4", "lr = -1.0"), "lr: must be > 0"),
        (
            ('init = "models/oibarnet.onnx"', 'init = "models/nope.onnx"'),
            "init: neither an earlier finetune stage nor a file",
        ),
        (
            ('init = "models/oibarnet.onnx"', 'init = "models/oibarnet.onnx"\ninit_sha256 = "abc"'),
            "64 lower-case hex",
        ),
        (("steps = 2", "steps = 2\nepochs = 1"), r"unknown key\(s\) \['epochs'\]"),
        (
            ('kind = "head_gain"\nmodel = "refit"', 'kind = "head_gain"\nmodel = "stage1"'),
            "of kind train, not",
        ),
        (
            ("range_edges_m = [0.0, 100.0]", "range_edges_m = [100.0, 0.0]"),
            "range_edges_m: two or more rising",
        ),
        (("min_frames = 16", "min_frames = 1"), "min_frames: >= 2"),
        (('priors = ["head"]', 'priors = ["direct"]'), "head_gain: only the head as a prior reads it"),
        (("sigma_scale = [1.0, 1000.0]", "sigma_scale = [1.0]"), "prior_sigma_scale: .*must have 2 entries"),
        (("sigma_scale = [1.0, 1000.0]", "sigma_scale = [1.0, 0.0]"), "prior_sigma_scale: .*within"),
        (("range_edges_m = [0.0, 3.0, 100.0], ", ""), "prior_sigma_scale: .*range_edges_m"),
        (
            ('pairs = [[2.0, 3.0]]\nhead_gain = "head_gain"', 'head_gain = "nope"'),
            "no earlier head_gain stage",
        ),
        (('kind = "retag"\nmodel = "refit"', 'kind = "retag"\nmodel = "head_gain"'), "not finetune"),
        (('kind = "retag"\nmodel = "refit"', 'kind = "retag"\nmodel = "stage1"'), "not finetune"),
        (('fusion = "fusion"', 'fusion = "head_gain"'), "fusion: 'head_gain' is a stage of kind head_gain"),
        (
            ('finder = "finder"', 'finder = "models/nope.onnx"'),
            "finder: neither an earlier finder stage nor a file",
        ),
        (
            ('finder = "finder"', 'finder = "fusion"'),
            "finder: 'fusion' is a stage of kind fusion, not finder",
        ),
        (('keypoints_from = "refit"', 'keypoints_from = "fusion"'), "keypoints_from: 'fusion' is a stage"),
        # a second fine-tune from the first's file, taught by another flight file
        (('init = "finetune"', 'init = "fusion"'), "init: neither an earlier finetune stage nor a file"),
        (('init = "finetune"', 'init = "stage1"'), "init: 'stage1' is a stage of kind train, not finetune"),
        (
            ('init = "finetune"', 'init = "finetune"\ninit_sha256 = "' + "0" * 64 + '"'),
            "init_sha256: 'finetune' is a stage, whose file the build makes",
        ),
        (
            ('distill_from = "models/oibarnet.onnx"', 'distill_from = "models/nope.onnx"'),
            "distill_from: not found",
        ),
        (
            (
                'distill_from = "models/oibarnet.onnx"',
                'distill_from = ""\ndistill_from_sha256 = "' + "0" * 64 + '"',
            ),
            "distill_from_sha256: pins no file",
        ),
        (
            (
                'distill_from = "models/oibarnet.onnx"',
                'distill_from = "models/oibarnet.onnx"\ndistill_from_sha256 = "x"',
            ),
            "distill_from_sha256: 64 lower-case hex",
        ),
        (
            (
                'val_data = "val"\n\n[[stages]]\nname = "retag"',
                'val_data = "train_dr"\n\n[[stages]]\nname = "retag"',
            ),
            "val_data: 'train_dr' is also trained on",
        ),
        (("finder_smoke.yaml", "finder_nope.yaml"), "config: not found"),
        # the head's crop gain: scenes of its set the fine-tune did not train on, read by the head
        (('scenes = ["tr001"]', 'scenes = ["tr001", "nope"]'), r"scenes: \['nope'\] are not in"),
        (('scenes = ["tr001"]', 'scenes = ["tr000"]'), r"scenes: \['tr000'\] are trained on by 'refit'"),
        (('scenes = ["tr001"]', "scenes = []"), "scenes: a list of distinct scene names"),
        (
            (
                'spec = "models/scenes/train.json"\nscenes = ["tr001"]',
                'spec = "models/scenes/nope.json"\nscenes = ["tr001"]',
            ),
            "spec: scene set not found",
        ),
        (
            (
                'head_crop_gain = "head_crop_gain"\npnp_alone',
                'head_crop_gain = "head_crop_gain"\nhead_gain = "head_gain"\npnp_alone',
            ),
            "head_crop_gain: not with head_gain",
        ),
        (
            ('head_crop_gain = "head_crop_gain"\npnp_alone', 'head_crop_gain = "head_gain"\npnp_alone'),
            "'head_gain' is a stage of kind head_gain, not head_crop_gain",
        ),
        (
            ('kind = "head_crop_gain"\nmodel = "refit"', 'kind = "head_crop_gain"\nmodel = "finetune"'),
            "'head_crop_gain' measured stage 'finetune''s model, not 'refit'",
        ),
        (
            ('fusion = "fusion_crop"\nhead_crop_gain = "head_crop_gain"', 'fusion = "fusion_crop"'),
            "head_crop_gain: '', but the fusion stage 'fusion_crop' chose its weights with 'head_crop_gain'",
        ),
        (('model = "retag"', 'model = "head_gain"'), "not export or finetune or retag"),
    ],
)
def test_a_bad_fine_tune_stage_is_refused_with_the_key_that_is_wrong(tmp_path, edit, match):
    old, new = edit
    text = FT_SMOKE.read_text().replace('[[stages]]\nname = "finetune"\n', TRAIN_STAGE, 1)
    assert old in text
    bad = tmp_path / "bad.toml"
    bad.write_text(text.replace(old, new, 1))
    with pytest.raises(RecipeError, match=match):
        load_recipe(bad)
    assert main([str(bad), "--runs", str(tmp_path / "runs"), "--no-progress"]) == 2
    assert not (tmp_path / "runs").exists()  # refused before anything ran


@pytest.fixture(scope="module")
def smoke(tmp_path_factory, tracking):
    runs = tmp_path_factory.mktemp("build_ft")
    b = Build(load_recipe(FT_SMOKE), runs, progress=False)
    b.run()
    return b


def test_a_crop_gain_on_scenes_an_earlier_fine_tune_in_the_chain_learnt_is_refused(tmp_path):
    """The refit trains on the randomised looks only; the fine-tune it starts from trained on
    tr000, so the crop gain may not be measured there either."""
    text = FT_SMOKE.read_text()
    refit = 'init = "finetune"\ntrain_data = ["train_base", "train_dr"]'
    assert refit in text and 'scenes = ["tr001"]' in text
    text = text.replace(refit, 'init = "finetune"\ntrain_data = ["train_dr"]', 1)
    held = 'distill_data = ["train_base"]\ndistill_from = "models/oibarnet.onnx"'
    assert held in text
    text = text.replace(held, 'distill_data = ["train_dr"]\ndistill_from = "models/oibarnet.onnx"', 1)
    ok = tmp_path / "ok.toml"
    ok.write_text(text)
    load_recipe(ok)  # tr001: no stage of the chain trained on it
    bad = tmp_path / "bad.toml"
    bad.write_text(text.replace('scenes = ["tr001"]', 'scenes = ["tr000"]', 1))
    with pytest.raises(RecipeError, match=r"scenes: \['tr000'\] are trained on by 'finetune'"):
        load_recipe(bad)


def test_the_smoke_candidate_is_a_flight_file_with_the_recipes_version_and_tables(smoke):
    from oibar.nav.pose import KeypointPoseEstimator, PoseEstimator, read_metadata
    from oibar_models.kp_export import load_fusion

    stages = [f"data_{n}" for n in smoke.recipe.datasets] + [s.name for s in smoke.recipe.stages]
    assert smoke.ran == stages and smoke.skipped == []
    for name in stages:
        marker = json.loads((smoke.stage_dir(name) / MARKER).read_text())
        assert marker["stage"] == name and len(marker["key"]) == 64
        for rel, sha in marker["outputs"].items():
            assert (smoke.dir / rel).is_file() and len(sha) == 64
    # the fine-tune: 2 steps from the shipped file, its training sequences in the recipe's order
    ft = read_metadata(smoke.stage_dir("finetune") / "oibarnet.onnx")["finetune"]
    shipped = read_metadata(REPO / "models/oibarnet.onnx")["model_version"]
    assert ft["steps"] == 2 and ft["seed"] == 7 and ft["from_model_version"] == shipped
    assert [Path(p).name for p in ft["data"]] == ["tr000", "dr000"] and [
        Path(p).name for p in ft["held"]
    ] == ["va013"]
    assert smoke.markers["finetune"]["metrics"]["steps"] == 2
    # the frozen attitude head: its weights as recovered from the shipped file, the rest trained
    import torch

    start = torch.load(smoke.stage_dir("finetune") / "recovered.pt", weights_only=False)["model"]
    end = torch.load(smoke.stage_dir("finetune") / "finetuned.pt", weights_only=False)["model"]
    assert ft["frozen"] == ["attitude"]
    moved = {k for k in start if start[k].is_floating_point() and not torch.equal(start[k], end[k])}
    assert any(k.startswith("attitude.") for k in start) and moved
    assert not {k for k in moved if k.startswith("attitude.")}
    assert {k.split(".")[0] for k in moved} >= {"backbone", "head"}
    # the distillation: the attitude head's answers on the base renderer's crops held to the start's
    assert ft["distill_weight_per_deg2"] == 1.0 and [Path(p).name for p in ft["distill_data"]] == ["tr000"]
    last = json.loads((smoke.stage_dir("finetune") / "log.jsonl").read_text().splitlines()[-1])
    assert last["distilled_crops"] > 0
    assert ft["distill_from"] == "models/oibarnet.onnx"  # its init, as the repository names it: its teacher
    assert ft["distill_start_gap_deg2"] == pytest.approx(0.0, abs=1e-9)
    # the map target's key, at its default, is not in the fingerprint (earlier builds still skip)
    assert ft["distill_target"] == "attitude" and "distill_weight_per_rel" not in ft
    assert "distill_target" not in smoke.markers["finetune"]["inputs"]["opts"]
    # nor is the rolled crops' share, which the file names only when it turned some
    assert "roll_share" not in smoke.markers["finetune"]["inputs"]["opts"] and "roll_share" not in ft
    # the refit: a second fine-tune from the first's file, the attitude head alone trained, its
    # answers held to the shipped file's, which the fine-tuned student does not start on
    refit = read_metadata(smoke.stage_dir("refit") / "oibarnet.onnx")["finetune"]
    assert refit["from"] == str(smoke.stage_dir("finetune") / "oibarnet.onnx")
    assert refit["from_model_version"] == f"{shipped}+finetune"
    assert refit["frozen"] == ["backbone", "lateral", "head", "present"]
    assert refit["distill_from"] == "models/oibarnet.onnx"
    assert refit["distill_start_gap_deg2"] > 1e-6
    start = torch.load(smoke.stage_dir("refit") / "recovered.pt", weights_only=False)["model"]
    end = torch.load(smoke.stage_dir("refit") / "finetuned.pt", weights_only=False)["model"]
    moved = {k for k in start if start[k].is_floating_point() and not torch.equal(start[k], end[k])}
    assert moved and {k.split(".")[0] for k in moved} == {"attitude"}
    assert smoke.markers["refit"]["inputs"]["upstream"]["finetune"] == smoke.markers["finetune"]["key"]
    # the head gain, one bin over every range (the toy's), within the flight code's limits
    gain = json.loads((smoke.stage_dir("head_gain") / "head_gain.json").read_text())
    assert gain["frames"] == 20 and gain["min_frames_per_bin"] == 16
    assert (
        gain["head_gain"]["range_edges_m"] == [0.0, 100.0] and 0.5 <= gain["head_gain"]["tilt_gain"][0] <= 2.0
    )
    fusion_doc = json.loads((smoke.stage_dir("fusion") / "fusion.json").read_text())
    assert fusion_doc["head_gain"] == gain["head_gain"]  # the grid weighed the head with that gain
    scale = {"range_edges_m": [0.0, 3.0, 100.0], "sigma_scale": [1.0, 1000.0]}  # the recipe's
    assert fusion_doc["prior_sigma_scale"] == scale
    # pnp_alone = false: every fusion scored carries the head prior
    assert fusion_doc["pnp_alone"] is False
    assert fusion_doc["grid"] and all(g["attitude_prior"] == "head" for g in fusion_doc["grid"])
    # the retagged file: the recipe's version, the fusion's choice and the gain, opened as flight opens it
    out = smoke.stage_dir("retag") / "oibarnet.onnx"
    est = PoseEstimator(out, warmup_runs=0)
    assert isinstance(est, KeypointPoseEstimator)
    meta = read_metadata(out)
    assert meta["model_version"] == "0.0.2" and "far_network" not in meta
    assert sorted(p.name for p in out.parent.glob("*.onnx")) == [
        "oibarnet.onnx",
        "oibarnet_finder.onnx",
        "oibarnet_lite.onnx",
    ]
    # the finder the recipe trained, labelled by the fine-tune's keypoints, beside and named by the file
    finder = smoke.stage_dir("finder") / "oibarnet_finder.onnx"
    assert meta["finder"] == {"file": "oibarnet_finder.onnx"}
    assert sha256_file(out.parent / "oibarnet_finder.onnx") == sha256_file(finder)
    fmeta = read_metadata(finder)
    assert fmeta["kind"] == "finder" and fmeta["model_version"] == "0.0.1"
    assert (
        est.search.finder is not None
        and smoke.markers["retag"]["metrics"]["finder"] == "oibarnet_finder.onnx"
    )
    cfg = json.loads((smoke.stage_dir("finder") / "config.yaml").read_text())
    assert [Path(s).name for s, _ in cfg["train_sets"]] == ["train_base.json", "train_dr.json"]
    assert cfg["seed"] == 7 and cfg["epochs"] == 1
    chosen = load_fusion(smoke.stage_dir("fusion") / "fusion.json", int(meta["crop"]["out_px"]))
    assert chosen is not None and chosen["attitude_prior"] == "head"
    assert meta["fusion"]["head_gain"] == gain["head_gain"]
    assert meta["fusion"]["prior_sigma_scale"] == scale
    assert est.fusion.prior_sigma_scale(meta["fusion"]).scale(5.0) == 1000.0
    for k in ("sigma_crop_px", "sigma_prior_deg", "kp_error_model", "prior_error_model"):
        assert meta["fusion"][k] == chosen[k], k
    assert smoke.markers["retag"]["metrics"]["head_gain"] is True
    # the head's crop gain: one bin probed at 0.5 and 6.25 m on a scene the fine-tune did not see,
    # the second fusion weighed the head with it, the second retag carries it and opens
    crop = json.loads((smoke.stage_dir("head_crop_gain") / "head_crop_gain.json").read_text())
    assert crop["scenes"] == ["tr001"] and crop["ranges_m"] == [0.5, 6.25] and crop["frames"] == 36
    assert crop["head_crop_gain"]["range_edges_m"] == [0.0, 100.0]
    assert 0.4 <= crop["head_crop_gain"]["gain"][0] <= 2.0
    assert smoke.markers["head_crop_gain"]["metrics"]["gain_0-100m"] == round(crop["bins"][0]["gain"], 4)
    crop_doc = json.loads((smoke.stage_dir("fusion_crop") / "fusion.json").read_text())
    assert crop_doc["head_crop_gain"] == crop["head_crop_gain"] and crop_doc["head_gain"] is None
    # the head's error model measured on the head as corrected (head_error = "as_used"), and in
    # that stage's fingerprint; the first fusion's as read, its key left out at that default
    assert crop_doc["head_error"] == "as-used" and fusion_doc["head_error"] == "as-read"
    assert smoke.markers["fusion_crop"]["inputs"]["opts"]["head_error"] == "as_used"
    assert "head_error" not in smoke.markers["fusion"]["inputs"]["opts"]
    assert crop_doc["best"]["head_crop_gain"] == crop["head_crop_gain"]
    out_crop = smoke.stage_dir("retag_crop") / "oibarnet.onnx"
    est_crop = PoseEstimator(out_crop, warmup_runs=0)
    fusion_crop = read_metadata(out_crop)["fusion"]
    assert fusion_crop["head_crop_gain"] == crop["head_crop_gain"] and "head_gain" not in fusion_crop
    assert est_crop.fusion.head_crop_gain(fusion_crop).gain[0] == crop["head_crop_gain"]["gain"][0]
    assert smoke.markers["retag_crop"]["metrics"]["head_crop_gain"] is True
    # unset, the key stays out of the other stages' fingerprints (earlier builds still skip)
    for name in ("fusion", "retag"):
        assert "head_crop_gain" not in smoke.markers[name]["inputs"]["opts"], name
    # evaluated through the flight estimator, as the recipe's evaluate stage says
    m = smoke.markers["evaluate"]["metrics"]
    assert m["mode"] == "track" and m["frames"] == 4
    for k in ("dt_mean_pct", "dq_mean_deg", "compliance_pos_pct", "compliance_att_pct"):
        assert isinstance(m[k], float) and math.isfinite(m[k]), (k, m)
    assert json.loads((smoke.stage_dir("evaluate") / "eval.json").read_text())["val"]


def test_the_fine_tune_and_its_measurements_are_in_mlflow(smoke, tracking):
    from mlflow.tracking import MlflowClient

    client = MlflowClient(tracking_uri=tracking)
    exp = client.get_experiment_by_name("oibarnet_kp_ft_smoke")
    by_stage = {r.data.tags["oibar.stage"]: r for r in client.search_runs([exp.experiment_id])}
    assert set(by_stage) == {
        "finetune",
        "refit",
        "head_gain",
        "fusion",
        "head_crop_gain",
        "fusion_crop",
        "evaluate",
    }
    assert {k: by_stage[k].data.tags["oibar.kind"] for k in by_stage} == {
        "finetune": "train",
        "refit": "train",
        "head_gain": "head_gain",
        "fusion": "fusion",
        "head_crop_gain": "head_crop_gain",
        "fusion_crop": "fusion",
        "evaluate": "evaluate",
    }
    assert by_stage["finetune"].data.params["train.seed"] == "7"
    assert {a.path for a in client.list_artifacts(by_stage["finetune"].info.run_id)} >= {
        "log.jsonl",
        "done.json",
    }
    hg = by_stage["head_gain"]
    assert hg.data.metrics["tilt_gain_0-100m"] == smoke.markers["head_gain"]["metrics"]["tilt_gain_0-100m"]
    assert "head_gain.json" in {a.path for a in client.list_artifacts(hg.info.run_id)}


def test_a_rerun_skips_every_stage_and_a_new_version_reruns_the_retag_and_what_reads_it(smoke):
    again = Build(smoke.recipe, smoke.dir.parent, progress=False)
    again.run()
    assert again.ran == [] and len(again.skipped) == len(smoke.recipe.datasets) + len(smoke.recipe.stages)
    bumped = Build(dataclasses.replace(smoke.recipe, model_version="0.0.3"), smoke.dir.parent, progress=False)
    bumped.run()
    assert bumped.ran == ["retag", "retag_crop", "evaluate"]
    from oibar.nav.pose import read_metadata

    assert read_metadata(smoke.stage_dir("retag") / "oibarnet.onnx")["model_version"] == "0.0.3"


def test_a_finder_stage_resumes_only_its_own_training(smoke):
    """The finder stage's folder holds the trainer's last.pt and frame caches between runs (an
    interrupted training resumes); a folder left by other inputs is emptied first, so a finder is
    never resumed from another recipe's training."""
    d = smoke.stage_dir("finder")
    (d / MARKER).unlink()  # as if interrupted
    stamp = (d / "finder_inputs.sha256").read_text()
    (d / "finder_inputs.sha256").write_text("0" * 64 + "\n")  # another recipe's training
    (d / "stale.npz").write_bytes(b"x")
    again = Build(smoke.recipe, smoke.dir.parent, progress=False)
    again.run(only="finder")
    assert "finder" in again.ran and not (d / "stale.npz").exists()
    assert (d / "finder_inputs.sha256").read_text() == stamp
    assert (d / "oibarnet_finder.onnx").is_file()
