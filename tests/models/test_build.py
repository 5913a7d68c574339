"""Recipes and the build (issue 61, item 1): a recipe is checked before anything runs; the smoke
recipe (models/recipes/oibarnet_kp_smoke.toml, the shipped recipe's stages at toy size) renders
its data, trains from ImageNet, exports a parity-checked two-network file, evaluates it, logs to
MLflow, skips every stage on a rerun, and gives the same figures from the same seed.

Cost: two smoke builds and a rerun, about 2-3 minutes on 2 shared CPU cores."""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import pytest

from oibar_models.build import MARKER, Build, main
from oibar_models.recipe import RecipeError, load_recipe

REPO = Path(__file__).resolve().parents[2]
FULL = REPO / "models/recipes/oibarnet_kp.toml"
SMOKE = REPO / "models/recipes/oibarnet_kp_smoke.toml"
FT = REPO / "models/recipes/oibarnet_kp_ft.toml"
FT_SMOKE = REPO / "models/recipes/oibarnet_kp_ft_smoke.toml"


def test_the_committed_recipes_load():
    full = load_recipe(FULL)
    assert full.model_version == "0.34.0"
    names = [s.name for s in full.stages]
    assert names[0] == "stage1" and full.stages[0]["init"] == "imagenet"
    assert {"stage15", "stage28", "fusion", "export", "evaluate", "card"} <= set(names)
    smoke = load_recipe(SMOKE)
    # the smoke recipe is the same chain: the same kinds of stage in the same order
    kinds = [s.kind for s in smoke.stages]
    assert kinds == ["train", "train", "train", "export", "fusion", "export", "evaluate", "card"]
    assert [s.kind for s in full.stages][-5:] == kinds[-5:]
    # the fine-tuned candidate's recipe and its smoke twin (tests/models/test_build_finetune.py)
    # (the smoke twin also trains a finder stage and refits the attitude head in a second
    # finetune stage, as the later candidates 0.35.8 and 0.35.9 do, and reads the head through its
    # crop gain in a second fusion and retag, as 0.35.13 does)
    ft = load_recipe(FT)
    later = {"refit", "head_crop_gain", "fusion_crop", "retag_crop"}
    assert ft.model_version == "0.35.3" and [s.kind for s in ft.stages] == [
        s.kind for s in load_recipe(FT_SMOKE).stages if s.kind != "finder" and s.name not in later
    ]


def test_every_stage_of_the_shipped_recipe_makes_a_valid_config(tmp_path):
    """Without a GPU the full recipe cannot run here; its plan can: every training stage's config
    as the build would run it loads, with disjoint train, validation and test sets, the recipe's
    seed, the init chain from ImageNet, and no wall-clock budget (which would make the steps,
    and so the model, depend on the machine's speed)."""
    b = Build(load_recipe(FULL), tmp_path, progress=False)
    configs = b.plan()
    assert list(configs) == [s.name for s in b.recipe.stages if s.kind == "train"] and len(configs) == 13
    for name, cfg in configs.items():
        assert cfg.train.seed == 0 and cfg.train.time_budget_s == 0, name
        assert Path(cfg.run_dir) == tmp_path / "oibarnet_kp" / name
    assert configs["stage1"].model.pretrained and not configs["stage1"].train.init_from
    assert configs["stage15"].train.init_from.endswith("stage13/best.pt")
    assert configs["stage28"].train.init_from.endswith("stage27/last.pt")
    assert configs["stage28"].data.train_spec == "" and configs["stage28"].data.far_only_spec.endswith(
        "train_sunfine.json"
    )
    assert configs["stage15"].data.train_root.endswith("data/train")  # the shared render folder
    assert not any((tmp_path / "oibarnet_kp" / n).exists() for n in configs)  # nothing ran


@pytest.mark.parametrize(
    "edit, match",
    [
        (("seed = 7", "seed = 7\nsneed = 1"), r"unknown key\(s\) \['sneed'\]"),
        (('model_version = "0.0.1"', 'model_version = "1.0"'), "MAJOR.MINOR.PATCH"),
        (("seed = 7", 'seed = "7"'), "recipe.seed: expected int"),
        (('init = "stage1:best"', 'init = "stage9:best"'), "no earlier train stage named 'stage9'"),
        (('init = "stage1:best"', 'init = "stage1:newest"'), "STAGE:best or STAGE:last"),
        (('"train.steps" = 2', '"train.seed" = 2'), "set by the build"),
        (
            ('scenes = ["va001"]', 'scenes = ["va001"]\nframe_limit = 3'),
            r"unknown key\(s\) \['frame_limit'\]",
        ),
        (('model = "draft"', 'model = "stage2"'), "is a stage of kind train, not export"),
        (('modes = ["track"]', 'modes = ["both"]'), "single and/or track"),
        (
            ('val_data = "val"\nstride = 1\nmodes', 'val_data = "test"\nstride = 1\nmodes'),
            "no dataset 'test'",
        ),
        (('kind = "card"', 'kind = "poster"'), "kind: one of"),
        (('spec = "models/scenes/val.json"', 'spec = "models/scenes/nope.json"'), "scene set not found"),
    ],
)
def test_a_bad_recipe_is_refused_with_the_key_that_is_wrong(tmp_path, edit, match):
    old, new = edit
    text = SMOKE.read_text()
    assert old in text
    bad = tmp_path / "bad.toml"
    bad.write_text(text.replace(old, new, 1))
    with pytest.raises(RecipeError, match=match):
        load_recipe(bad)
    assert main([str(bad), "--runs", str(tmp_path / "runs")]) == 2
    assert not (tmp_path / "runs").exists()  # refused before anything ran


def test_a_recipe_that_is_not_toml_is_refused(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text("[recipe\nname = 1\n")
    with pytest.raises(RecipeError, match="not valid TOML"):
        load_recipe(bad)


@pytest.fixture(scope="module")
def smoke(tmp_path_factory, tracking):
    runs = tmp_path_factory.mktemp("build")
    b = Build(load_recipe(SMOKE), runs, progress=False)
    b.run()
    return b


def test_the_smoke_build_exports_a_checked_model_with_finite_metrics(smoke):
    import torch

    from oibar.nav.pose import KeypointPoseEstimator, PoseEstimator, read_metadata

    stages = ["data_train", "data_val", *(s.name for s in smoke.recipe.stages)]
    assert smoke.ran == stages and smoke.skipped == []
    for name in stages:
        marker = json.loads((smoke.stage_dir(name) / MARKER).read_text())
        assert marker["stage"] == name and len(marker["key"]) == 64
        # where it ran, for a rebuild that does not match to the bit
        assert marker["machine"]["torch"] == torch.__version__
        assert marker["machine"]["cpu_capability"] == torch.backends.cpu.get_cpu_capability()
        for rel, sha in marker["outputs"].items():
            assert (smoke.dir / rel).is_file() and len(sha) == 64
    out = smoke.stage_dir("export") / "oibarnet.onnx"
    assert smoke.markers["export"]["metrics"]["parity_checked"] is True
    meta = read_metadata(out)
    assert meta["model_version"] == "0.0.1" and meta["far_network"] == {
        "file": "oibarnet_far.onnx",
        "from_m": 8.0,
    }
    assert meta["fusion"]["attitude_prior"] == "head"  # the fusion stage's choice went into the file
    assert isinstance(PoseEstimator(out, warmup_runs=0), KeypointPoseEstimator)
    m = smoke.markers["evaluate"]["metrics"]
    assert m["mode"] == "track" and m["frames"] == 4
    for k in ("dt_mean_pct", "dq_mean_deg", "compliance_pos_pct", "compliance_att_pct"):
        assert isinstance(m[k], float) and math.isfinite(m[k]), (k, m)
    # the card stage: the tables and an entry the registry can take
    import tomllib

    entry = tomllib.loads((smoke.stage_dir("card") / "entry.toml").read_text())["models"][0]
    assert entry["metrics"]["validation"]["dq_mean_deg"] == m["dq_mean_deg"]
    assert set(entry["files"]) == {
        "export/oibarnet.onnx",
        "export/oibarnet_far.onnx",
        "export/oibarnet_lite.onnx",
    }
    assert set(entry["datasets"]) == {"train", "val"}
    assert "rebuild" in (smoke.stage_dir("card") / "card.md").read_text()
    assert smoke.markers["card"]["metrics"] == {"registered": False}  # no rule to hold a smoke build to


def test_every_training_and_evaluation_stage_is_in_mlflow(smoke, tracking):
    from mlflow.tracking import MlflowClient

    client = MlflowClient(tracking_uri=tracking)
    exp = client.get_experiment_by_name("oibarnet_kp_smoke")
    runs = client.search_runs([exp.experiment_id])
    by_stage = {r.data.tags["oibar.stage"]: r for r in runs}
    assert set(by_stage) == {"stage1", "stage2", "far", "fusion", "evaluate"}
    assert by_stage["fusion"].data.tags["oibar.kind"] == "fusion"
    train = by_stage["stage1"]
    assert train.data.params["train.seed"] == "7" and train.data.params["model.pretrained"] == "True"
    assert math.isfinite(train.data.metrics["val_kp_err_crop_px_mean"])
    ev = by_stage["evaluate"]
    assert ev.data.metrics["dq_mean_deg"] == smoke.markers["evaluate"]["metrics"]["dq_mean_deg"]
    assert {a.path for a in client.list_artifacts(ev.info.run_id)} >= {"eval.json", "metrics.json"}
    assert Path(ev.info.artifact_uri.removeprefix("file://")).is_relative_to(Path(tracking[10:]).parent)


def test_a_rerun_skips_every_stage_and_a_lost_stage_reruns_alone(smoke):
    again = Build(smoke.recipe, smoke.dir.parent, progress=False)
    again.run()
    assert again.ran == [] and len(again.skipped) == 2 + len(smoke.recipe.stages)
    # a training stage stopped after its last checkpoint (no marker yet) resumes from it: no
    # step is trained again (the trainer's log gains no row), and nothing after it reruns
    log = smoke.stage_dir("far") / "log.jsonl"
    rows = log.read_text()
    (smoke.stage_dir("far") / MARKER).unlink()
    resumed = Build(smoke.recipe, smoke.dir.parent, progress=False)
    resumed.run()
    assert resumed.ran == ["far"] and log.read_text() == rows
    assert resumed.markers["far"]["outputs"] == smoke.markers["far"]["outputs"]
    # a stage whose output changed (or was lost) reruns, and what reads it after it
    (smoke.stage_dir("evaluate") / "metrics.json").write_text("{}")
    third = Build(smoke.recipe, smoke.dir.parent, progress=False)
    third.run()
    assert third.ran == ["evaluate"]  # the card reads the metrics, which came out the same
    assert third.markers["evaluate"]["metrics"] == smoke.markers["evaluate"]["metrics"]


def test_the_same_seed_gives_the_same_networks(smoke, tmp_path):
    """A second build from the same recipe, on the first one's frames (the rendering is checked
    by their hashes) and through its training stages: the same weights, bit for bit, and the same
    validation figures. (The evaluation's repeat is the rerun test's.)"""
    import dataclasses

    import torch

    shared = {
        n: dataclasses.replace(d, root=str(smoke.dataset_root(d))) for n, d in smoke.recipe.datasets.items()
    }
    other = Build(dataclasses.replace(smoke.recipe, datasets=shared), tmp_path, progress=False)
    other.run(only="far")
    for name in ("data_train", "data_val"):
        assert other.markers[name]["metrics"] == smoke.markers[name]["metrics"]  # the frames' hashes
    for name in ("stage1", "stage2", "far"):
        assert other.markers[name]["metrics"] == smoke.markers[name]["metrics"], name
        for ck in ("best.pt", "last.pt"):  # the weights, tensor for tensor (best.pt also holds its paths)
            a = torch.load(smoke.stage_dir(name) / ck, map_location="cpu", weights_only=False)["model"]
            b = torch.load(other.stage_dir(name) / ck, map_location="cpu", weights_only=False)["model"]
            assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a), (name, ck)
    assert "draft" not in other.markers  # --only stops after the stage it names
    shutil.rmtree(tmp_path / smoke.recipe.name)


def test_training_augmentation_is_seeded(tiny_dataset):
    """kp_data's training crops (window jitter, photometric terms, mirror) repeat for the same
    run seed and torch seed, and differ when either changes (issue 61: they were unseeded)."""
    import torch

    from oibar.geometry.fixture import keypoints_m
    from oibar_models.kp_data import CropAugment, CropDataset, open_scenes

    scenes = open_scenes(tiny_dataset, ["seq02"])

    def draws(seed: int, torch_seed: int) -> list:
        torch.manual_seed(torch_seed)
        ds = CropDataset(scenes, keypoints_m(), 64, CropAugment(p_mirror=0.5), train=True, seed=seed)
        return [ds[i]["image"] for i in (0, 3, 0)]

    a, b = draws(1, 5), draws(1, 5)
    assert all(torch.equal(x, y) for x, y in zip(a, b, strict=True))
    assert not torch.equal(a[0], a[2])  # the same frame drawn twice is augmented anew
    assert not torch.equal(a[0], draws(2, 5)[0]) and not torch.equal(a[0], draws(1, 6)[0])
