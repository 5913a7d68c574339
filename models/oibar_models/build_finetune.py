"""The recipe stages of a candidate fine-tuned from a flight file, run by oibar_models.build
(Build.finetune, Build.head_gain, Build.finder, Build.retag) through its `step`: fingerprinted
inputs (the recipe's keys, the files read by content, the upstream stages' and datasets' keys), a
done marker, skipped on a rerun whose inputs match.

    finetune   oibar_models.finetune's steps 1-3 (kp_recover, the trainer's loop, the export with
               every table of the starting file) on the recipe's rendered datasets; the recipe's
               seed is the fine-tune's. Its own evaluation is not run: an evaluate stage measures
               the candidate. -> oibarnet.onnx with its first pass (and far network unless
               far_network = false), finetuned.pt, recovered.pt, config.yaml, log.jsonl, done.json
    head_gain  kp_head_gain on a finetune's or export's file -> head_gain.json
    head_crop_gain  kp_head_crop_gain on a finetune's or export's file, on probe frames of the
               scenes the recipe names (rendered by the rig camera) -> head_crop_gain.json
    finder     oibar_models.finder's train and export under a finder config, on the recipe's
               datasets, labelled by a keypoint stage's file; resumes -> oibarnet_finder.onnx
    retag      a finetune's file, the graph untouched, with a fusion stage's weights, a head_gain
               or head_crop_gain stage's table, an optional fixture finder (a finder stage's, or a committed file)
               and the recipe's model_version
               (kp_export.retag), its companions beside it, opened as the flight runtime opens it
               -> oibarnet.onnx, the flight file of the candidate

The finetune and head_gain stages are logged to MLflow as the trainer and the evaluations are
(oibar_models.tracking; OIBAR_TRACKING=0 turns it off).
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from typing import TYPE_CHECKING, Any

from oibar.hashing import sha256_file

from .build import BuildError, fingerprint
from .recipe import STAGE_KEYS, Stage, resolve

if TYPE_CHECKING:
    from .build import Build

MODEL_FILE = "oibarnet.onnx"  # what a finetune, export or retag stage writes in its folder


def model_file(b: Build, stage: str) -> Path:
    return b.stage_dir(stage) / MODEL_FILE


# finetune keys left out of its fingerprint at their defaults (recipe.STAGE_KEYS), added after
# builds that lacked them
UNSET_KEYS = (
    "roll_share",
    "freeze",
    "distill_weight",
    "distill_data",
    "distill_from",
    "distill_from_sha256",
    "distill_target",
)


def folders(b: Build, name: str) -> list[Path]:
    """A dataset's sequence folders, its scenes in its own order."""
    ds = b.recipe.datasets[name]
    specs, _ = b.scene_list(ds)
    return [b.dataset_root(ds) / s.name for s in specs]


def sequences(b: Build, st: Stage) -> tuple[list[Path], list[Path]]:
    """A finetune stage's training sequence folders, in order (its datasets as listed, each
    dataset's scenes in its own order), and its held ones."""
    return [p for name in st["train_data"] for p in folders(b, name)], folders(b, st["val_data"])


def clear(d: Path) -> None:
    """A stage that does not resume starts from an empty folder: no file of an earlier run (a far
    network since dropped, say) lies beside its outputs."""
    for p in d.iterdir():
        if p.is_file():
            p.unlink()


# ----------------------------------------------------------------------------- finetune
def finetune(b: Build, st: Stage) -> dict:
    from dataclasses import asdict

    from oibar.nav.pose import ModelFileError, read_metadata

    from . import tracking
    from .config import ConfigError
    from .data import DatasetError
    from .finetune import FinetuneError, Options, companions, fine_tuned, stage_config
    from .kp_recover import RecoverError

    o = st.opts
    init_stage = o["init"] if any(s.name == o["init"] for s in b.recipe.stages) else ""  # its file
    init = model_file(b, init_stage) if init_stage else resolve(o["init"])
    init_sha = pinned(st, init, o["init_sha256"])
    teacher = resolve(o["distill_from"]) if o["distill_from"] else None
    teacher_sha = pinned(st, teacher, o["distill_from_sha256"]) if teacher else ""
    try:
        meta = read_metadata(init)
    except ModelFileError as exc:
        raise BuildError(f"stage {st.name}: init: {exc}") from exc
    train, held = sequences(b, st)
    opts = Options(
        data=train,
        val=held,
        init=init,
        out=b.stage_dir(st.name),
        steps=o["steps"],
        batch_size=o["batch_size"],
        lr=o["lr"],
        seed=b.recipe.seed,
        far_network=o["far_network"],
        threads=b.recipe.threads,
        progress=b.progress,
        force=True,  # the marker, not the folder, says whether the stage is done
        batch_norm=o["batch_norm"],
        freeze=tuple(o["freeze"]),
        distill_weight=o["distill_weight"],
        distill_data=tuple(p for name in o["distill_data"] for p in folders(b, name)),
        distill_from=teacher,
        distill_target=o["distill_target"],
        roll_share=o["roll_share"],
        config=stage_config_of(b, init_stage) if init_stage else None,
        note=f"a candidate of recipe {b.recipe.name} (stage {st.name}): it ships only once judged and registered",
    )
    kept = dict(meta)
    if not o["far_network"]:
        kept.pop("far_network", None)
    try:
        cfg, _ = stage_config(opts, meta, 0)  # `steps`, not epochs: the frame count is not read
        beside = {name: sha256_file(init.parent / name) for name in companions(kept)}
    except (FinetuneError, ConfigError, KeyError) as exc:
        raise BuildError(f"stage {st.name}: {exc}") from exc
    except OSError as exc:
        raise BuildError(f"stage {st.name}: a file {init.name} names is not beside it: {exc}") from exc
    inputs = {
        # a stage that freezes and distils nothing fingerprints as it did before those keys existed
        "opts": {k: v for k, v in o.items() if k not in UNSET_KEYS or v != STAGE_KEYS["finetune"][k][1]},
        "init_sha256": init_sha,
        "companions_sha256": beside,
        "config": asdict(cfg),
        "threads": b.recipe.threads,
        "upstream": b.upstream(*(f"data_{n}" for n in o["train_data"]), f"data_{o['val_data']}", init_stage),
        **({"distill_from_sha256": teacher_sha} if teacher else {}),
    }

    def run(d: Path):
        clear(d)
        try:
            cfg, candidate, _ = fine_tuned(opts)
        except (FinetuneError, DatasetError, ConfigError, RecoverError, ModelFileError) as exc:
            raise BuildError(f"stage {st.name}: {exc}") from exc
        done = json.loads((d / "done.json").read_text())
        metrics: dict[str, Any] = {"steps": done["steps"]}
        metrics |= {f"val_{k}": v for k, v in done["last"].items() if isinstance(v, (int, float))}
        spreads = read_metadata(candidate)["finetune"]["spread_median_crop_px"]
        metrics |= {f"spread_median_crop_px_{k}": v for k, v in spreads.items()}
        tracking.log_training(b.recipe, st.name, cfg, d, metrics)
        outputs = [candidate, *(d / n for n in companions(read_metadata(candidate))), d / "finetuned.pt"]
        return outputs, metrics

    return b.step(st.name, "finetune", inputs, run)


def stage_config_of(b: Build, stage: str) -> Path:
    """The network config an earlier finetune stage derived its own from: a fine-tuned file's
    oibar.name is its run's, which names no config of models/configs."""
    import yaml

    return Path(yaml.safe_load((b.stage_dir(stage) / "config.yaml").read_text())["derived_from"])


def pinned(st: Stage, path: Path, pin: str) -> str:
    """`path`'s sha256, checked against the recipe's pin ("": not pinned)."""
    sha = sha256_file(path)
    if pin and pin != sha:
        raise BuildError(f"stage {st.name}: {path} hashes {sha[:12]}..., the recipe pins {pin[:12]}...")
    return sha


# ----------------------------------------------------------------------------- head gains
def _gain_stage(
    b: Build, st: Stage, inputs: dict, argv_of, measure_main, keys: tuple[str, ...], plot: bool
) -> dict:
    """A head_gain or head_crop_gain stage: its measurement's command line (`argv_of(model)` and
    the bins, frames and output every such command takes) run into <kind>.json, each bin's `keys`
    as the stage's metrics, logged to MLflow."""
    from . import tracking

    o, kind = st.opts, st.kind

    def run(d: Path):
        out = d / f"{kind}.json"
        model = model_file(b, o["model"])
        argv = [*argv_of(model), "--min-frames", str(inputs["min_frames"])]
        argv += ["--range-edges", ",".join(repr(e) for e in inputs["range_edges_m"])]
        argv += ["--out", str(out), "--no-progress"]
        outputs = [out]
        if plot:
            argv += ["--plot", str(d / f"{kind}.png")]
            outputs.append(d / f"{kind}.png")
        if measure_main(argv) != 0:
            raise BuildError(f"stage {st.name}: the {kind} measurement failed (kp_{kind} {' '.join(argv)})")
        doc = json.loads(out.read_text())
        metrics: dict[str, Any] = {"frames": doc["frames"]}
        for row in doc["bins"]:
            lo, hi = row["range_m"]
            for key in keys:
                metrics[f"{key}_{lo:g}-{hi:g}m"] = round(row[key], 4)
        tracking.log_evaluation(b.recipe, st.name, model, d, metrics, o, kind=kind)
        return outputs, metrics

    return b.step(st.name, kind, inputs, run)


def head_gain(b: Build, st: Stage) -> dict:
    from .kp_fusion import ERROR_RANGE_EDGES_M
    from .kp_head_gain import MIN_FRAMES_PER_BIN
    from .kp_head_gain import main as head_gain_main

    o = st.opts
    spec, root = b.val_set(st)
    inputs = {
        "opts": o,
        "range_edges_m": [float(e) for e in (o["range_edges_m"] or ERROR_RANGE_EDGES_M)],  # the defaults then
        "min_frames": o["min_frames"] or MIN_FRAMES_PER_BIN,
        "upstream": b.upstream(o["model"], f"data_{o['val_data']}"),
    }

    def argv_of(model: Path) -> list[str]:
        return ["--model", str(model), "--val-set", str(spec), str(root), "--stride", str(o["stride"])]

    return _gain_stage(b, st, inputs, argv_of, head_gain_main, ("tilt_gain",), plot=False)


def head_crop_gain(b: Build, st: Stage) -> dict:
    from .kp_fusion import ERROR_RANGE_EDGES_M
    from .kp_head_crop_gain import MIN_FRAMES_PER_BIN, bin_ranges_m
    from .kp_head_crop_gain import main as crop_gain_main

    o = st.opts
    spec = resolve(o["spec"])
    edges = [float(e) for e in (o["range_edges_m"] or ERROR_RANGE_EDGES_M)]
    inputs = {
        "opts": o,
        "spec_sha256": sha256_file(spec),  # the scenes as the rig renders them
        "range_edges_m": edges,  # what the defaults were when it ran
        "ranges_m": bin_ranges_m(edges),
        "min_frames": o["min_frames"] or MIN_FRAMES_PER_BIN,
        "upstream": b.upstream(o["model"]),
    }

    def argv_of(model: Path) -> list[str]:
        return ["--model", str(model), "--spec", str(spec), "--scenes", ",".join(o["scenes"])]

    return _gain_stage(b, st, inputs, argv_of, crop_gain_main, ("gain", "bearing_leak"), plot=True)


# ----------------------------------------------------------------------------- finder
FINDER_FILE = "oibarnet_finder.onnx"  # what a finder stage writes; the flight file names it


def finder(b: Build, st: Stage) -> dict:
    """The fixture finder trained on the recipe's datasets (oibar_models.finder's train and
    export), its boxes labelled by a keypoint stage's file, its epoch chosen on val_data. An
    interrupted training resumes from its last epoch; one with other inputs starts afresh."""
    from dataclasses import asdict, replace

    from . import finder as F
    from .config import ConfigError

    o = st.opts
    try:
        cfg = F.load_finder_config(resolve(o["config"]))
    except ConfigError as exc:
        raise BuildError(f"stage {st.name}: {exc}") from exc
    d = b.stage_dir(st.name)
    val = b.recipe.datasets[o["val_data"]]
    cfg = replace(
        cfg,
        keypoints_from=str(model_file(b, o["keypoints_from"])),
        train_sets=[
            [str(b.dataset_spec(b.recipe.datasets[n])), str(b.dataset_root(b.recipe.datasets[n]))]
            for n in o["train_data"]
        ],
        val_set=[str(b.dataset_spec(val)), str(b.dataset_root(val))],
        out_dir=str(d),
        seed=b.recipe.seed,
        threads=b.recipe.threads,
    )  # its own model_version: a new candidate version does not retrain it
    inputs = {
        "opts": o,
        "config": asdict(cfg),
        "upstream": b.upstream(
            o["keypoints_from"], *(f"data_{n}" for n in o["train_data"]), f"data_{o['val_data']}"
        ),
    }

    def run(d: Path):
        key = fingerprint(inputs)
        stamp = d / "finder_inputs.sha256"  # whose training last.pt and the caches belong to
        if not stamp.is_file() or stamp.read_text().strip() != key:
            shutil.rmtree(d)
            d.mkdir(parents=True)
            stamp.write_text(key + "\n")
        try:
            best = F.train(cfg, progress=b.progress)
            out = F.export(cfg, d / FINDER_FILE)
        except (ConfigError, FileNotFoundError) as exc:
            raise BuildError(f"stage {st.name}: {exc}") from exc
        # the trainer logs its own run to MLflow (experiment: the finder config's name)
        return [out], {k: v for k, v in best.items() if isinstance(v, (int, float))}

    return b.step(st.name, "finder", inputs, run)


# ----------------------------------------------------------------------------- retag
def retag(b: Build, st: Stage) -> dict:
    o = st.opts
    src = model_file(b, o["model"])
    fusion_file = b.stage_dir(o["fusion"]) / "fusion.json" if o["fusion"] else None
    gain_file = b.stage_dir(o["head_gain"]) / "head_gain.json" if o["head_gain"] else None
    crop_file = b.stage_dir(o["head_crop_gain"]) / "head_crop_gain.json" if o["head_crop_gain"] else None
    finder_stage = o["finder"] if any(s.name == o["finder"] for s in b.recipe.stages) else ""
    finder = None
    if finder_stage:
        finder = b.stage_dir(finder_stage) / FINDER_FILE
    elif o["finder"]:
        finder = resolve(o["finder"])
    inputs = {
        # head_crop_gain and keypoints_any_turn unset fingerprint as before the keys existed
        "opts": {k: v for k, v in o.items() if k not in ("head_crop_gain", "keypoints_any_turn") or v},
        "model_version": b.recipe.model_version,
        "finder_sha256": sha256_file(finder) if finder else "",
        "upstream": b.upstream(o["model"], o["fusion"], o["head_gain"], o["head_crop_gain"], finder_stage),
    }

    def run(d: Path):
        from oibar.nav.pose import KeypointPoseEstimator, ModelFileError, PoseEstimator, read_metadata

        from .finetune import companions
        from .kp_export import load_fusion, load_head_crop_gain, load_head_gain
        from .kp_export import retag as retag_file

        clear(d)
        meta = read_metadata(src)
        written = []
        for name in companions(meta):  # the first pass (and far network) the file names, beside it
            shutil.copy(src.parent / name, d / name)
            written.append(d / name)
        options: dict[str, Any] = {"model_version": b.recipe.model_version}
        if o["keypoints_any_turn"]:
            options["keypoints_any_turn"] = True
        try:
            if fusion_file:
                # PnP alone when the grid chose no prior: no weights, as an export without fusion
                options["fusion"] = load_fusion(fusion_file, int(meta["crop"]["out_px"])) or {}
            prior = (options.get("fusion", meta.get("fusion")) or {}).get("attitude_prior")
            for key, path, load in (
                ("head_gain", gain_file, load_head_gain),
                ("head_crop_gain", crop_file, load_head_crop_gain),
            ):
                if path is None:
                    continue
                table = load(path)
                if prior == "head":
                    options[key] = table
                else:  # kp_fusion's own rule: its choice carries the gain only with the head as prior
                    b.say(f"{st.name}: the fusion's prior is {prior or 'none'}, not the head: no {key}")
        except (OSError, ValueError, KeyError) as exc:
            raise BuildError(f"stage {st.name}: {exc}") from exc
        if finder:
            shutil.copy(finder, d / finder.name)
            options["finder"] = {"file": finder.name}
            written.append(d / finder.name)
        out = d / MODEL_FILE
        try:
            retag_file(src, out, options)
            est = PoseEstimator(out, warmup_runs=1)  # checked as flight opens it, its files beside it
        except (ModelFileError, ValueError, OSError) as exc:
            raise BuildError(f"stage {st.name}: the retagged file does not open: {exc}") from exc
        if not isinstance(est, KeypointPoseEstimator):
            raise BuildError(f"stage {st.name}: {out} is not a keypoint model")
        new = read_metadata(out)
        fusion = new.get("fusion") or {}
        metrics = {
            "model_version": new["model_version"],
            "attitude_prior": fusion.get("attitude_prior", "direct") if fusion else "none",
            "head_gain": bool(fusion.get("head_gain")),
            "head_crop_gain": bool(fusion.get("head_crop_gain")),
            "finder": finder.name if finder else "",
            "onnx_mib": round(out.stat().st_size / 2**20, 2),
        }
        return [out, *written], metrics

    return b.step(st.name, "retag", inputs, run)
