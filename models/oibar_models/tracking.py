"""Experiment tracking with MLflow: every training and evaluation stage of a build is one MLflow
run (experiment = the recipe's name, run name = the stage's) with its parameters, its metrics
(each validation row of the trainer's log.jsonl at its step) and its files.

Where the runs go: $MLFLOW_TRACKING_URI when set (a tracking server, or any store MLflow knows),
else the local SQLite store DEFAULT_STORE under runs/ (git-ignored), its files beside it in
runs/mlflow/artifacts. SQLite, not MLflow's old ./mlruns folder store: MLflow 3 keeps that one in
maintenance mode and refuses it unless told otherwise. The first use creates the database (about
10 s). To look: `mlflow ui --backend-store-uri sqlite:///runs/mlflow/mlflow.db` with the full
`mlflow` package (the pinned mlflow-skinny logs but has no UI). OIBAR_TRACKING=0 turns logging
off (a build then only writes its run folder).
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import Any

from .config import REPO_ROOT

DEFAULT_STORE = REPO_ROOT / "runs" / "mlflow" / "mlflow.db"
# files small enough to keep with every run; checkpoints stay in the run folder (hashed in its marker)
TRAIN_ARTEFACTS = ("config.yaml", "log.jsonl", "done.json")
EVAL_ARTEFACTS = ("eval.json", "eval.md", "metrics.json", "fusion.json", "head_gain.json")


class TrackingError(RuntimeError):
    """MLflow is not installed or its store cannot be written."""


def enabled() -> bool:
    return os.environ.get("OIBAR_TRACKING", "1") != "0"


def tracking_uri() -> str:
    uri = os.environ.get("MLFLOW_TRACKING_URI")
    if uri:
        return uri
    DEFAULT_STORE.parent.mkdir(parents=True, exist_ok=True)
    return f"sqlite:///{DEFAULT_STORE}"


def artefact_root(uri: str) -> str | None:
    """Where a new experiment keeps its files: beside a local SQLite store (MLflow's own default
    is ./mlruns in whatever folder the command ran from); a server's own choice otherwise."""
    if uri.startswith("sqlite:///"):
        return (Path(uri[len("sqlite:///") :]).parent / "artifacts").as_uri()
    return None


def _mlflow():
    try:
        import mlflow
    except ImportError as exc:
        raise TrackingError(
            "MLflow is not installed (requirements/ml.txt: run `make setup`), or set OIBAR_TRACKING=0"
        ) from exc
    mlflow.set_tracking_uri(tracking_uri())
    return mlflow


def flatten(d: dict, prefix: str = "") -> dict[str, str]:
    """{'train': {'lr': 1e-3}} -> {'train.lr': '0.001'}; MLflow params are strings (500 chars)."""
    out: dict[str, str] = {}
    for k, v in d.items():
        key = f"{prefix}{k}"
        if isinstance(v, dict):
            out.update(flatten(v, key + "."))
        else:
            out[key] = str(v)[:500]
    return out


def finite(metrics: dict[str, Any]) -> dict[str, float]:
    """The numbers MLflow can store (it refuses neither NaN nor inf, but they plot as nothing)."""
    return {
        k: float(v)
        for k, v in metrics.items()
        if isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(float(v))
    }


def _run(recipe, stage: str, params: dict[str, str], tags: dict[str, str]):
    mlflow = _mlflow()
    if mlflow.get_experiment_by_name(recipe.name) is None:
        mlflow.create_experiment(recipe.name, artifact_location=artefact_root(mlflow.get_tracking_uri()))
    mlflow.set_experiment(recipe.name)
    return (
        mlflow,
        mlflow.start_run(
            run_name=stage,
            tags={
                "oibar.recipe": str(recipe.path),
                "oibar.stage": stage,
                "oibar.seed": str(recipe.seed),
                **tags,
            },
        ),
        params,
    )


def log_training(recipe, stage: str, cfg, run_dir: Path, best: dict) -> str | None:
    """One training stage: its config as params, each validation row as metrics at its step."""
    if not enabled():
        return None
    from dataclasses import asdict

    mlflow, active, params = _run(recipe, stage, flatten(asdict(cfg)), {"oibar.kind": "train"})
    with active as run:
        mlflow.log_params(params)
        log = run_dir / "log.jsonl"
        for line in log.read_text().splitlines() if log.is_file() else []:
            row = json.loads(line)
            step = int(row.get("step", 0))
            mlflow.log_metrics(finite({k: v for k, v in row.items() if k != "step"}), step=step)
        mlflow.log_metrics(finite({f"best_{k}": v for k, v in best.items()}))
        for name in TRAIN_ARTEFACTS:
            if (run_dir / name).is_file():
                mlflow.log_artifact(str(run_dir / name))
        return str(run.info.run_id)


def log_evaluation(
    recipe, stage: str, model: Path, out_dir: Path, metrics: dict, opts: dict, kind: str = "evaluate"
) -> str | None:
    """One evaluation stage (or a selection on validation, kind "fusion"): the model file's hash as
    a param, the paper's metrics, its tables."""
    if not enabled():
        return None
    from .build import sha256_file

    params = flatten({"model": str(model), "model_sha256": sha256_file(model), **opts})
    mlflow, active, params = _run(recipe, stage, params, {"oibar.kind": kind})
    with active as run:
        mlflow.log_params(params)
        mlflow.log_metrics(finite(metrics))
        for name in EVAL_ARTEFACTS:
            if (out_dir / name).is_file():
                mlflow.log_artifact(str(out_dir / name))
        return str(run.info.run_id)
