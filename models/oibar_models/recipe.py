"""A model's recipe: one TOML file (models/recipes/*.toml) that says everything `python -m
oibar_models.build` needs to go from the ImageNet backbone and the data generator to the exported,
checked ONNX file. Validated before anything runs: an unknown key, a missing one, a value of the
wrong type or a stage that names a stage it cannot use is a RecipeError naming the file and key.

    [recipe]    name, model_version, seed, description, threads
    [datasets.NAME]   spec (a scene set, models/scenes/*.json), root, scenes, frames_limit
    [[stages]]  name, kind, and the keys of its kind (STAGE_KEYS):
      train     a keypoint training stage (a kp_engine YAML config): from the ImageNet backbone
                (init = "imagenet") or another train stage's checkpoint (init = "STAGE:best|last")
      export    one or two trained networks to the flight file (kp_export), parity-checked and
                opened as the flight runtime opens it
      fusion    the fit's weights chosen on validation (kp_fusion's grid) for an export's or a
                fine-tune's file, optionally with a head_gain stage's table
      evaluate  the flight estimator on the validation set (kp_evaluate): the paper's metrics
      card      the model card's tables and a registry entry for the build, from an evaluate stage
    and, for a candidate fine-tuned from a flight file (oibar_models.build_finetune):
      finetune  an ONNX file (init, its sha256 pinned by init_sha256) or an earlier finetune
                stage's file fine-tuned on a list of datasets (oibar_models.finetune: recovered,
                trained, exported with its tables), optionally with the attitude head distilled
                from init or from another flight file (distill_from)
      head_gain the attitude head's tilt gain per range bin on validation (kp_head_gain)
      head_crop_gain  the attitude head's gain and bearing leak in its crop per range bin, on
                probe frames of training scenes the fine-tune did not train on (kp_head_crop_gain)
      finder    the fixture finder (oibar_models.finder: a finder config's network and schedule)
                trained on the recipe's datasets, labelled by a keypoint stage's file, exported
      retag     a fine-tune's file with a fusion stage's weights, a head_gain or head_crop_gain
                stage's table, an optional fixture finder (a finder stage or a file) and the
                recipe's model_version (kp_export.retag), opened as the flight runtime opens it
"""

from __future__ import annotations

import math
import re
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from .config import REPO_ROOT


class RecipeError(ValueError):
    """A recipe file is missing, not TOML, or holds unknown keys or values that cannot work."""


VERSION_RE = re.compile(r"\d+\.\d+\.\d+")
NAME_RE = re.compile(r"[a-z][a-z0-9_]*")
STAGE_KINDS = (
    "train",
    "export",
    "fusion",
    "evaluate",
    "card",
    "finetune",
    "head_gain",
    "head_crop_gain",
    "finder",
    "retag",
)
# the kinds whose stage folder holds a flight file, oibarnet.onnx with its companions
MODEL_KINDS = ("export", "finetune", "retag")
BATCH_NORM = ("frozen", "train")  # oibar_models.finetune.BATCH_NORM (not imported: it loads torch)
FREEZABLE = ("backbone", "lateral", "head", "present", "attitude")  # oibar_models.finetune.FREEZABLE
DISTILL_TARGETS = ("attitude", "last_tap")  # oibar_models.finetune.DISTILL_TARGETS
HEAD_ERROR = ("as_read", "as_used")  # a fusion stage's head_error (kp_fusion --head-error)
# every key a stage of each kind may have (beyond name and kind), with its type and default;
# None as a default: required
STAGE_KEYS: dict[str, dict[str, tuple[type | tuple[type, ...], Any]]] = {
    "train": {
        "config": (str, None),
        "init": (str, None),  # "imagenet" or "STAGE:best|last"
        "train_data": (str, ""),  # a dataset: the config's data.train_spec
        "far_only_data": (str, ""),  # a dataset: the config's data.far_only_spec
        "val_data": (str, None),
        "overrides": (dict, {}),
        "note": (str, ""),
    },
    "export": {
        "network": (str, None),  # "STAGE:best|last"
        "far_network": (str, ""),  # "STAGE:best|last": read every window from far_from_m on
        "far_from_m": (float, 8.0),
        "first_pass": (str, "models/oibarnet_lite.onnx"),
        "first_pass_sha256": (str, ""),
        "fusion": (str, ""),  # a fusion stage, a kp_fusion JSON file, or "" for PnP with the prior off
        "corner_refine_side_px": (float, -1.0),  # -1: the config's
        "note": (str, ""),
    },
    "fusion": {
        "model": (str, None),  # an export or finetune stage
        "val_data": (str, None),
        "stride": (int, 16),
        "priors": (list, ["direct", "head"]),
        "pairs": (list, []),  # [[KP_PX, PRIOR_DEG], ...]; empty: the whole grid
        "head_gain": (str, ""),  # a head_gain stage measured on the same model: the head's tilt divided by it
        "head_crop_gain": (str, ""),  # a head_crop_gain stage on the same model (not with head_gain)
        # {range_edges_m = [...], sigma_scale = [...]}: a factor on the prior's sigma by range, chosen
        # on the validation probe (oibar.fusion.prior_sigma_scale); {}: the error model's weight
        "prior_sigma_scale": (dict, {}),
        "pnp_alone": (bool, True),  # PnP alone scored beside the priors; false: the fusion carries one
        # the head prior's error model measured on the head as the fit uses it (gain given back:
        # "as_used") or as read ("as_read", what every recipe written before 2026-12-07 built with)
        "head_error": (str, "as_read"),
        "note": (str, ""),
    },
    "evaluate": {
        "model": (str, None),  # an export, finetune or retag stage
        "val_data": (str, None),
        "stride": (int, 2),
        "modes": (list, ["track"]),
        "note": (str, ""),
    },
    "card": {
        "evaluate": (str, None),
        "note": (str, ""),
    },
    "finetune": {
        # a keypoint flight file (repository path), its companions beside it, or an earlier
        # finetune stage (its file)
        "init": (str, None),
        "init_sha256": (str, ""),  # checked when the stage runs; "": not pinned (a stage's: never)
        "train_data": (list, None),  # datasets, in order: their scenes are the training sequences
        "val_data": (str, None),  # the held sequences (the trainer's crop validation only)
        "steps": (int, 1000),  # finetune.STEPS
        "lr": (float, 4e-4),  # finetune.LR (every recipe so far names its own rate)
        "batch_size": (int, 16),
        "batch_norm": (str, "frozen"),  # BATCH_NORM
        "far_network": (bool, True),  # keep init's far network beside the candidate
        "freeze": (list, []),  # FREEZABLE parts kept as init has them
        "distill_weight": (
            float,
            0.0,
        ),  # per deg^2 (finetune.DISTILL_WEIGHT), or per unit of relative difference (last_tap)
        "distill_data": (list, []),  # of train_data, whose crops it holds; []: every one
        "distill_from": (str, ""),  # the teacher, a keypoint flight file; "": init
        "distill_from_sha256": (str, ""),  # checked when the stage runs; "": not pinned
        "distill_target": (str, "attitude"),  # DISTILL_TARGETS: the head's answers or the last map
        "roll_share": (float, 0.0),  # share of crops turned by any angle (kp_data.CropAugment.p_roll)
        "note": (str, ""),
    },
    "head_gain": {
        "model": (str, None),  # a finetune or export stage
        "val_data": (str, None),
        "stride": (int, 4),
        "min_frames": (int, 0),  # the fewest frames per range bin; 0: kp_head_gain.MIN_FRAMES_PER_BIN
        "range_edges_m": (list, []),  # the bins' rising edges; []: kp_fusion.ERROR_RANGE_EDGES_M
        "note": (str, ""),
    },
    "head_crop_gain": {
        "model": (str, None),  # a finetune or export stage
        "spec": (str, None),  # a scene set (models/scenes/*.json): rendered by the rig, not the build
        "scenes": (list, None),  # its scenes probed: ones the model's fine-tune did not train on
        "min_frames": (int, 0),  # the fewest frames per range bin; 0: kp_head_crop_gain.MIN_FRAMES_PER_BIN
        "range_edges_m": (list, []),  # the bins' rising edges; []: kp_fusion.ERROR_RANGE_EDGES_M
        "note": (str, ""),
    },
    "finder": {
        # a finder config (models/configs/finder/*.yaml): its network, schedule and augmentation
        "config": (str, None),
        "keypoints_from": (str, None),  # a finetune, export or retag stage: its keypoints label the boxes
        "train_data": (list, None),  # datasets, in order (the config's train_sets are not read)
        "val_data": (str, None),  # the epoch is chosen on it (the config's val_set is not read)
        "note": (str, ""),
    },
    "retag": {
        "model": (str, None),  # a finetune stage
        "fusion": (str, ""),  # a fusion stage on the same model; "": the model's own weights
        "head_gain": (str, ""),  # a head_gain stage on the same model; "": the model's own table
        "head_crop_gain": (str, ""),  # a head_crop_gain stage on the same model (not with head_gain)
        "finder": (str, ""),  # a finder stage, or a finder ONNX (repository path), copied beside; "": none
        # the model's keypoints read any turn (a fine-tune with roll_share)
        "keypoints_any_turn": (bool, False),
        "note": (str, ""),
    },
}


@dataclass
class Dataset:
    name: str
    spec: str  # a scene set (models/scenes/*.json), repository-relative or absolute
    root: str = ""  # where it is rendered; "": runs/<recipe>/data/<name>
    scenes: list[str] = field(default_factory=list)  # a subset of the spec's scenes; []: all
    frames_limit: int = 0  # the first N frames of each scene; 0: all


@dataclass
class Stage:
    name: str
    kind: str
    opts: dict[str, Any]

    def __getitem__(self, key: str) -> Any:
        return self.opts[key]


@dataclass
class Recipe:
    path: Path
    name: str
    model_version: str
    seed: int
    description: str
    threads: int
    runs_dir: str
    datasets: dict[str, Dataset]
    stages: list[Stage]

    def stage(self, name: str) -> Stage:
        for s in self.stages:
            if s.name == name:
                return s
        raise KeyError(name)


def resolve(p: str | Path) -> Path:
    q = Path(p)
    return q if q.is_absolute() else REPO_ROOT / q


def _typed(where: str, value: Any, want: type | tuple[type, ...]) -> Any:
    if want is float and isinstance(value, int) and not isinstance(value, bool):
        return float(value)
    if isinstance(value, bool) and want is not bool:
        raise RecipeError(f"{where}: expected {getattr(want, '__name__', want)}, got {value!r}")
    if not isinstance(value, want):
        raise RecipeError(f"{where}: expected {getattr(want, '__name__', want)}, got {value!r}")
    return value


def _only(where: str, table: dict, known: set[str]) -> None:
    unknown = sorted(set(table) - known)
    if unknown:
        raise RecipeError(f"{where}: unknown key(s) {unknown}; known: {sorted(known)}")


def split_ref(ref: str, where: str) -> tuple[str, str]:
    """'STAGE:best|last' -> (STAGE, best|last)."""
    stage, _, which = ref.partition(":")
    if not stage or which not in ("best", "last"):
        raise RecipeError(f"{where}: expected STAGE:best or STAGE:last, got {ref!r}")
    return stage, which


def load_recipe(path: str | Path) -> Recipe:
    """Read and check a recipe; RecipeError with the file and key on anything wrong."""
    path = Path(path)
    try:
        doc = tomllib.loads(path.read_text())
    except OSError as exc:
        raise RecipeError(f"{path}: cannot read the recipe ({exc})") from exc
    except tomllib.TOMLDecodeError as exc:
        raise RecipeError(f"{path}: not valid TOML ({exc})") from exc
    w = str(path)
    _only(w, doc, {"recipe", "datasets", "stages"})
    head = doc.get("recipe")
    if not isinstance(head, dict):
        raise RecipeError(f"{w}: a [recipe] table is required")
    _only(f"{w} [recipe]", head, {"name", "model_version", "seed", "description", "threads", "runs_dir"})
    for key in ("name", "model_version", "seed"):
        if key not in head:
            raise RecipeError(f"{w} [recipe]: {key} is required")
    name = _typed(f"{w} recipe.name", head["name"], str)
    if not NAME_RE.fullmatch(name):
        raise RecipeError(f"{w} recipe.name: lower case, digits and _ only, got {name!r}")
    version = _typed(f"{w} recipe.model_version", head["model_version"], str)
    if not VERSION_RE.fullmatch(version):
        raise RecipeError(f"{w} recipe.model_version: MAJOR.MINOR.PATCH, got {version!r}")
    seed = _typed(f"{w} recipe.seed", head["seed"], int)
    if seed < 0:
        raise RecipeError(f"{w} recipe.seed: must be >= 0, got {seed}")
    threads = _typed(f"{w} recipe.threads", head.get("threads", 2), int)
    if threads < 1:
        raise RecipeError(f"{w} recipe.threads: must be >= 1, got {threads}")

    datasets: dict[str, Dataset] = {}
    raw_sets = doc.get("datasets", {})
    if not isinstance(raw_sets, dict) or not raw_sets:
        raise RecipeError(f"{w}: at least one [datasets.NAME] table is required")
    for dname, d in raw_sets.items():
        where = f"{w} [datasets.{dname}]"
        if not NAME_RE.fullmatch(dname) or not isinstance(d, dict):
            raise RecipeError(f"{where}: a table named in lower case, digits and _")
        _only(where, d, {"spec", "root", "scenes", "frames_limit"})
        if "spec" not in d:
            raise RecipeError(f"{where}: spec is required (a scene set, models/scenes/*.json)")
        ds = Dataset(
            dname,
            _typed(f"{where} spec", d["spec"], str),
            _typed(f"{where} root", d.get("root", ""), str),
            list(_typed(f"{where} scenes", d.get("scenes", []), list)),
            _typed(f"{where} frames_limit", d.get("frames_limit", 0), int),
        )
        if not resolve(ds.spec).is_file():
            raise RecipeError(f"{where} spec: scene set not found: {ds.spec}")
        if ds.frames_limit < 0:
            raise RecipeError(f"{where} frames_limit: must be >= 0 (0: every frame), got {ds.frames_limit}")
        if not all(isinstance(s, str) for s in ds.scenes):
            raise RecipeError(f"{where} scenes: a list of scene names")
        datasets[dname] = ds

    stages: list[Stage] = []
    raw_stages = doc.get("stages", [])
    if not isinstance(raw_stages, list) or not raw_stages:
        raise RecipeError(f"{w}: at least one [[stages]] entry is required")
    for i, s in enumerate(raw_stages):
        where = f"{w} stages[{i}]"
        if not isinstance(s, dict) or "name" not in s or "kind" not in s:
            raise RecipeError(f"{where}: every stage has a name and a kind")
        sname = _typed(f"{where} name", s["name"], str)
        where = f"{w} stage {sname!r}"
        if not NAME_RE.fullmatch(sname):
            raise RecipeError(f"{where}: a name in lower case, digits and _")
        if any(x.name == sname for x in stages) or sname in ("data",):
            raise RecipeError(f"{where}: the name is used twice (or is reserved)")
        kind = s["kind"]
        if kind not in STAGE_KINDS:
            raise RecipeError(f"{where} kind: one of {list(STAGE_KINDS)}, got {kind!r}")
        spec = STAGE_KEYS[kind]
        opts = {k: v for k, v in s.items() if k not in ("name", "kind")}
        _only(where, opts, set(spec))
        for key, (typ, default) in spec.items():
            if key in opts:
                opts[key] = _typed(f"{where} {key}", opts[key], typ)
            elif default is None:
                raise RecipeError(f"{where}: {key} is required for a {kind} stage")
            else:
                opts[key] = default
        _check_stage(where, kind, opts, stages, datasets)
        stages.append(Stage(sname, kind, opts))
    return Recipe(
        path=path,
        name=name,
        model_version=version,
        seed=seed,
        description=str(head.get("description", "")),
        threads=threads,
        runs_dir=_typed(f"{w} recipe.runs_dir", head.get("runs_dir", "runs"), str),
        datasets=datasets,
        stages=stages,
    )


def _earlier(where: str, key: str, ref: str, before: list[Stage], kind: str | tuple[str, ...]) -> Stage:
    kinds = (kind,) if isinstance(kind, str) else kind
    for s in before:
        if s.name == ref:
            if s.kind not in kinds:
                raise RecipeError(
                    f"{where} {key}: {ref!r} is a stage of kind {s.kind}, not {' or '.join(kinds)}"
                )
            return s
    raise RecipeError(
        f"{where} {key}: no earlier {' or '.join(kinds)} stage named {ref!r} (stages run in file order)"
    )


def _same_model(where: str, key: str, ref: str, model: str, before: list[Stage]) -> None:
    """A head_gain or fusion stage `ref` named by a stage that reads `model` measured that model."""
    up = next(s for s in before if s.name == ref)
    if up["model"] != model:
        raise RecipeError(f"{where} {key}: {ref!r} measured stage {up['model']!r}'s model, not {model!r}")


def _dataset(where: str, key: str, name: str, datasets: dict[str, Dataset]) -> None:
    if name and name not in datasets:
        raise RecipeError(f"{where} {key}: no dataset {name!r} (known: {sorted(datasets)})")


def _check_stage(where: str, kind: str, o: dict, before: list[Stage], datasets: dict[str, Dataset]) -> None:
    if kind == "train":
        if not resolve(o["config"]).is_file():
            raise RecipeError(f"{where} config: not found: {o['config']}")
        if o["init"] != "imagenet":
            stage, _ = split_ref(o["init"], f"{where} init")
            _earlier(where, "init", stage, before, "train")
        if not o["train_data"] and not o["far_only_data"]:
            raise RecipeError(f"{where}: train_data or far_only_data is required (nothing to train on)")
        for key in ("train_data", "far_only_data", "val_data"):
            _dataset(where, key, o[key], datasets)
        for key, value in o["overrides"].items():
            if key.split(".")[0] not in ("data", "model", "augment", "train", "export"):
                raise RecipeError(f"{where} overrides: {key!r} is not SECTION.KEY of a keypoint config")
            if key in ("train.seed", "train.init_from", "model.pretrained", "run_dir") or isinstance(
                value, dict
            ):
                raise RecipeError(f"{where} overrides: {key!r} is set by the build (seed, init, run folder)")
    elif kind == "export":
        _earlier(where, "network", split_ref(o["network"], f"{where} network")[0], before, "train")
        if o["far_network"]:
            _earlier(
                where, "far_network", split_ref(o["far_network"], f"{where} far_network")[0], before, "train"
            )
            if not o["far_from_m"] > 0:
                raise RecipeError(f"{where} far_from_m: must be > 0, got {o['far_from_m']}")
        if not resolve(o["first_pass"]).is_file():
            raise RecipeError(f"{where} first_pass: not found: {o['first_pass']}")
        if o["fusion"] and not any(s.name == o["fusion"] for s in before):
            if not o["fusion"].endswith(".json") or not resolve(o["fusion"]).is_file():
                raise RecipeError(
                    f"{where} fusion: neither an earlier fusion stage nor a kp_fusion JSON file: {o['fusion']!r}"
                )
        elif o["fusion"]:
            _earlier(where, "fusion", o["fusion"], before, "fusion")
    elif kind in ("fusion", "evaluate", "head_gain"):
        model_kinds = {"fusion": ("export", "finetune"), "head_gain": ("export", "finetune")}.get(
            kind, MODEL_KINDS
        )
        _earlier(where, "model", o["model"], before, model_kinds)
        if not o["val_data"]:
            raise RecipeError(f"{where} val_data: a dataset is required")
        _dataset(where, "val_data", o["val_data"], datasets)
        if o["stride"] < 1:
            raise RecipeError(f"{where} stride: must be >= 1, got {o['stride']}")
        if kind == "head_gain":
            _check_head_gain(where, o)
        elif kind == "fusion":
            if o["head_gain"]:
                _earlier(where, "head_gain", o["head_gain"], before, "head_gain")
                _same_model(where, "head_gain", o["head_gain"], o["model"], before)
                if "head" not in o["priors"]:
                    raise RecipeError(
                        f"{where} head_gain: only the head as a prior reads it; priors {o['priors']!r}"
                    )
            _check_crop_gain_ref(where, o, before)
            if not o["priors"] or any(p not in ("direct", "head") for p in o["priors"]):
                raise RecipeError(f"{where} priors: direct and/or head, got {o['priors']!r}")
            for p in o["pairs"]:
                if not (
                    isinstance(p, list)
                    and len(p) == 2
                    and all(isinstance(x, (int, float)) and x > 0 for x in p)
                ):
                    raise RecipeError(f"{where} pairs: [[KP_PX, PRIOR_DEG], ...], each > 0, got {p!r}")
            if o["head_error"] not in HEAD_ERROR:
                raise RecipeError(
                    f"{where} head_error: one of {', '.join(HEAD_ERROR)}, got {o['head_error']!r}"
                )
            if o["prior_sigma_scale"]:
                from oibar.nav.error_models import PriorSigmaScale

                try:
                    PriorSigmaScale(o["prior_sigma_scale"])
                except (KeyError, TypeError, ValueError) as exc:
                    raise RecipeError(
                        f"{where} prior_sigma_scale: {{range_edges_m = [...], sigma_scale = [...]}}, "
                        f"one factor per bin ({exc})"
                    ) from None
        elif not o["modes"] or any(m not in ("single", "track") for m in o["modes"]):
            raise RecipeError(f"{where} modes: single and/or track, got {o['modes']!r}")
    elif kind == "card":
        _earlier(where, "evaluate", o["evaluate"], before, "evaluate")
    elif kind == "finetune":
        _check_finetune(where, o, datasets, before)
    elif kind == "retag":
        _earlier(where, "model", o["model"], before, "finetune")
        if o["fusion"]:
            fusion = _earlier(where, "fusion", o["fusion"], before, "fusion")
            _same_model(where, "fusion", o["fusion"], o["model"], before)
            if o["head_gain"] and fusion["head_gain"] and fusion["head_gain"] != o["head_gain"]:
                raise RecipeError(
                    f"{where} head_gain: {o['head_gain']!r}, but the fusion stage {o['fusion']!r} "
                    f"chose its weights with {fusion['head_gain']!r}"
                )
            if o["head_crop_gain"] != fusion["head_crop_gain"]:
                raise RecipeError(
                    f"{where} head_crop_gain: {o['head_crop_gain']!r}, but the fusion stage {o['fusion']!r} "
                    f"chose its weights with {fusion['head_crop_gain']!r}"
                )
        if o["head_gain"]:
            _earlier(where, "head_gain", o["head_gain"], before, "head_gain")
            _same_model(where, "head_gain", o["head_gain"], o["model"], before)
        _check_crop_gain_ref(where, o, before)
        if o["finder"] and any(s.name == o["finder"] for s in before):
            _earlier(where, "finder", o["finder"], before, "finder")
        elif o["finder"] and not resolve(o["finder"]).is_file():
            raise RecipeError(f"{where} finder: neither an earlier finder stage nor a file: {o['finder']}")
    elif kind == "finder":
        _check_finder(where, o, before, datasets)
    elif kind == "head_crop_gain":
        _check_head_crop_gain(where, o, before, datasets)


def _check_crop_gain_ref(where: str, o: dict, before: list[Stage]) -> None:
    """A fusion or retag stage's head_crop_gain: an earlier head_crop_gain stage on its model,
    not beside a head_gain, read only by the head as a prior."""
    if not o["head_crop_gain"]:
        return
    _earlier(where, "head_crop_gain", o["head_crop_gain"], before, "head_crop_gain")
    _same_model(where, "head_crop_gain", o["head_crop_gain"], o["model"], before)
    if o["head_gain"]:
        raise RecipeError(f"{where} head_crop_gain: not with head_gain (one correction of the head, not two)")
    if "priors" in o and "head" not in o["priors"]:
        raise RecipeError(
            f"{where} head_crop_gain: only the head as a prior reads it; priors {o['priors']!r}"
        )


def _spec_scene_names(where: str, spec: str) -> list[str]:
    import json

    try:
        doc = json.loads(resolve(spec).read_text())
    except (OSError, ValueError) as exc:
        raise RecipeError(f"{where} spec: cannot read the scene set {spec} ({exc})") from None
    items = doc.get("scenes", []) if isinstance(doc, dict) else doc
    return [str(s.get("name", "")) for s in items if isinstance(s, dict)]


def _check_head_crop_gain(where: str, o: dict, before: list[Stage], datasets: dict[str, Dataset]) -> None:
    model = _earlier(where, "model", o["model"], before, ("export", "finetune"))
    _check_head_gain(where, o)
    if not resolve(o["spec"]).is_file():
        raise RecipeError(f"{where} spec: scene set not found: {o['spec']}")
    names = o["scenes"]
    if not names or not all(isinstance(n, str) and n for n in names) or len(set(names)) != len(names):
        raise RecipeError(f"{where} scenes: a list of distinct scene names, got {names!r}")
    known = set(_spec_scene_names(where, o["spec"]))
    unknown = [n for n in names if n not in known]
    if unknown:
        raise RecipeError(f"{where} scenes: {unknown} are not in {o['spec']}")
    # a calibration on scenes the fine-tune learnt would flatter its head: the model's fine-tune
    # and every earlier one it starts from (its init chain)
    stage: Stage | None = model
    while stage is not None and stage.kind == "finetune":
        for dname in stage["train_data"]:
            ds = datasets[dname]
            if resolve(ds.spec).resolve() != resolve(o["spec"]).resolve():
                continue
            seen = set(ds.scenes) if ds.scenes else known
            if seen & set(names):
                raise RecipeError(
                    f"{where} scenes: {sorted(seen & set(names))} are trained on by {stage.name!r} (dataset {dname!r})"
                )
        stage = next((s for s in before if s.name == stage["init"]), None)


def _check_finder(where: str, o: dict, before: list[Stage], datasets: dict[str, Dataset]) -> None:
    if not resolve(o["config"]).is_file():
        raise RecipeError(f"{where} config: not found: {o['config']}")
    _earlier(where, "keypoints_from", o["keypoints_from"], before, MODEL_KINDS)
    _check_train_val(where, o, datasets)


def _check_train_val(where: str, o: dict, datasets: dict[str, Dataset]) -> None:
    """A stage's train_data (a list of distinct datasets) and val_data (another one)."""
    train = o["train_data"]
    if not train or not all(isinstance(n, str) and n for n in train):
        raise RecipeError(f"{where} train_data: a list of one or more dataset names, got {train!r}")
    for n in train:
        _dataset(where, "train_data", n, datasets)
    if len(set(train)) != len(train):
        raise RecipeError(f"{where} train_data: a dataset named twice in {train!r}")
    if not o["val_data"]:
        raise RecipeError(f"{where} val_data: a dataset is required")
    _dataset(where, "val_data", o["val_data"], datasets)
    if o["val_data"] in train:
        raise RecipeError(f"{where} val_data: {o['val_data']!r} is also trained on (train_data)")


def _check_finetune(where: str, o: dict, datasets: dict[str, Dataset], before: list[Stage]) -> None:
    if any(s.name == o["init"] for s in before):
        _earlier(where, "init", o["init"], before, "finetune")
        if o["init_sha256"]:
            raise RecipeError(f"{where} init_sha256: {o['init']!r} is a stage, whose file the build makes")
    elif not resolve(o["init"]).is_file():
        raise RecipeError(f"{where} init: neither an earlier finetune stage nor a file: {o['init']}")
    for key in ("init_sha256", "distill_from_sha256"):
        if o[key] and not re.fullmatch(r"[0-9a-f]{64}", o[key]):
            raise RecipeError(f"{where} {key}: 64 lower-case hex digits, got {o[key]!r}")
    _check_train_val(where, o, datasets)
    if o["steps"] < 1 or o["batch_size"] < 1:
        raise RecipeError(f"{where} steps, batch_size: must be >= 1, got {o['steps']}, {o['batch_size']}")
    if not o["lr"] > 0:
        raise RecipeError(f"{where} lr: must be > 0, got {o['lr']}")
    if o["batch_norm"] not in BATCH_NORM:
        raise RecipeError(f"{where} batch_norm: one of {list(BATCH_NORM)}, got {o['batch_norm']!r}")
    freeze = o["freeze"]
    if not all(isinstance(p, str) and p in FREEZABLE for p in freeze) or len(set(freeze)) != len(freeze):
        raise RecipeError(f"{where} freeze: distinct parts of {list(FREEZABLE)}, got {freeze!r}")
    if set(freeze) == set(FREEZABLE):
        raise RecipeError(f"{where} freeze: every part frozen leaves nothing to train")
    w, held = o["distill_weight"], o["distill_data"]
    if not (w >= 0 and math.isfinite(w)):
        raise RecipeError(f"{where} distill_weight: a finite number >= 0, got {w!r}")
    if held and not w > 0:
        raise RecipeError(f"{where} distill_data: given with no distill_weight (> 0)")
    if o["distill_from"] and not w > 0:
        raise RecipeError(f"{where} distill_from: given with no distill_weight (> 0)")
    if o["distill_from"] and not resolve(o["distill_from"]).is_file():
        raise RecipeError(f"{where} distill_from: not found: {o['distill_from']}")
    if not 0.0 <= o["roll_share"] <= 1.0:
        raise RecipeError(f"{where} roll_share: a share in [0, 1], got {o['roll_share']}")
    if o["distill_target"] not in DISTILL_TARGETS:
        raise RecipeError(
            f"{where} distill_target: one of {list(DISTILL_TARGETS)}, got {o['distill_target']!r}"
        )
    if o["distill_target"] != "attitude" and not w > 0:
        raise RecipeError(f"{where} distill_target: given with no distill_weight (> 0)")
    if o["distill_from_sha256"] and not o["distill_from"]:
        raise RecipeError(f"{where} distill_from_sha256: pins no file (distill_from is not set)")
    if not all(isinstance(n, str) and n in o["train_data"] for n in held) or len(set(held)) != len(held):
        raise RecipeError(
            f"{where} distill_data: distinct datasets of train_data {o['train_data']!r}, got {held!r}"
        )


def _check_head_gain(where: str, o: dict) -> None:
    if o["min_frames"] != 0 and o["min_frames"] < 2:
        raise RecipeError(f"{where} min_frames: >= 2 (0: the measurement's own), got {o['min_frames']}")
    edges = o["range_edges_m"]
    if edges and (
        len(edges) < 2
        or not all(isinstance(e, (int, float)) and not isinstance(e, bool) and e >= 0 for e in edges)
        or any(b <= a for a, b in zip(edges[:-1], edges[1:], strict=True))
    ):
        raise RecipeError(f"{where} range_edges_m: two or more rising edges >= 0 (m), got {edges!r}")
