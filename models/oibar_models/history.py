"""The record before the tracker: the files that lived in docs/data (204 JSON and JSONL files of
evaluations, probes, closed-loop flights, ship verdicts, fusion grids and training logs, from
OibarNet 0.8.1 to 0.34.0) imported from git history into MLflow, one run per file in the
experiment "history".

    python -m oibar_models.history import [--rev GIT_REV] [--dir FOLDER] [--repo PATH]

--rev: the commit to read them from (`git show REV:docs/data/NAME`); default the last commit that
had them (the newest commit touching docs/data, or the one before it that did when that commit
removed them).
--dir: a folder of such files instead of git (a checkout that still has them). Each run keeps its
file as an artefact and is tagged with its source path, the commit and the file's sha256; a file
already imported (same name and sha256) is skipped, so running it again adds nothing. Metrics
where a file's shape makes them plain: an evaluation ({"val"|"test": {model: {sequence:
{metric: value}}}}) as "set/model/sequence/metric", a ship-rule part's verdict as `holds`, a
training log (kp_train_*_log.jsonl) as per-step metrics; top-level numbers of any file as they are.

The store is the build's (oibar_models.tracking): $MLFLOW_TRACKING_URI, else runs/mlflow/mlflow.db.
What the shipped model needs from those files is not here but beside the registry
(models/registry.toml, models/registry/NAME-VERSION/).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import re
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from .config import REPO_ROOT
from .tracking import TrackingError, artefact_root, finite, tracking_uri

EXPERIMENT = "history"
HISTORY_PATH = "docs/data"
SUFFIXES = (".json", ".jsonl")
BATCH = 1000  # MLflow's log_batch takes at most 1000 metrics a call


class HistoryError(RuntimeError):
    """No commit has the files, a rev or folder cannot be read, or git is missing."""


# ----------------------------------------------------------------------------- reading the files
def _git(repo: Path, *args: str) -> bytes:
    try:
        out = subprocess.run(["git", "-C", str(repo), *args], check=True, capture_output=True)
    except FileNotFoundError as exc:
        raise HistoryError("git is not installed") from exc
    except subprocess.CalledProcessError as exc:
        msg = exc.stderr.decode(errors="replace").strip()
        raise HistoryError(f"git {' '.join(args)}: {msg}") from exc
    return out.stdout


def names_at(repo: Path, rev: str, path: str = HISTORY_PATH) -> list[str]:
    """The JSON and JSONL files under `path` at `rev` (file names, sorted)."""
    out = _git(repo, "ls-tree", "-r", "--name-only", rev, "--", path + "/").decode()
    return sorted(Path(p).name for p in out.splitlines() if p.endswith(SUFFIXES))


def last_rev_with_files(repo: Path, path: str = HISTORY_PATH) -> str:
    """The newest commit whose tree has files under `path`: the newest commit touching it, or, when
    that one removed them, the one before it that touched it (its tree there is the parent's)."""
    for rev in _git(repo, "log", "--format=%H", "--", path).decode().split():
        if names_at(repo, rev, path):
            return rev
    raise HistoryError(f"no commit in {repo} has files under {path}/")


def from_git(repo: Path, rev: str, path: str = HISTORY_PATH) -> Iterator[tuple[str, bytes]]:
    names = names_at(repo, rev, path)
    if not names:
        raise HistoryError(f"{rev} has no JSON files under {path}/")
    for name in names:
        yield name, _git(repo, "show", f"{rev}:{path}/{name}")


def from_dir(folder: Path) -> Iterator[tuple[str, bytes]]:
    files = sorted(p for p in Path(folder).iterdir() if p.is_file() and p.name.endswith(SUFFIXES))
    if not files:
        raise HistoryError(f"{folder}: no JSON files")
    for p in files:
        yield p.name, p.read_bytes()


# ----------------------------------------------------------------------------- what a file says
def family(name: str) -> str:
    """The kind of record, from the file's name (the prefixes docs/data used)."""
    if name.startswith("kp_train_") and name.endswith(".jsonl"):
        return "train_log"
    for prefix in (
        "eval_",
        "probe_",
        "loop_",
        "judge_",
        "kp_fusion",
        "kp_head_gain",
        "gate_choice",
        "scan_shrink",
        "study_",
    ):
        if name.startswith(prefix):
            return prefix.rstrip("_")
    return "other"


def _key(*parts: Any) -> str:
    """An MLflow metric name: letters, digits, _ - . / and spaces only, 250 characters at most."""
    return re.sub(r"[^\w.\-/ ]", "_", "/".join(str(p) for p in parts))[:250]


def eval_metrics(doc: Any) -> dict[str, float]:
    """{"val"|"test": {model: {sequence: {metric: number}}}} -> {"set/model/sequence/metric": number}
    (the per-range "_bins" left in the artefact); {} for any other shape."""
    if not isinstance(doc, dict) or not doc or not set(doc) <= {"val", "test"}:
        return {}
    out: dict[str, Any] = {}
    for set_name, models in doc.items():
        for model, seqs in (models or {}).items() if isinstance(models, dict) else ():
            for seq, metrics in (seqs or {}).items() if isinstance(seqs, dict) else ():
                if isinstance(metrics, dict):
                    for k, v in metrics.items():
                        if not k.startswith("_"):
                            out[_key(set_name, model, seq, k)] = v
    return finite(out)


def file_metrics(name: str, doc: Any) -> dict[str, float]:
    """The metrics a JSON file's shape makes plain (see the module's docstring)."""
    out = eval_metrics(doc)
    if isinstance(doc, dict):
        out.update(finite({_key(k): v for k, v in doc.items() if not isinstance(v, bool)}))
        if family(name) == "judge" and isinstance(doc.get("holds"), bool):
            out["holds"] = float(doc["holds"])
    return out


def log_rows(data: bytes) -> list[tuple[int, dict[str, float]]]:
    """A training log (one JSON object a line, with its "step") as (step, metrics)."""
    rows = []
    for line in data.decode().splitlines():
        if line.strip():
            row = json.loads(line)
            rows.append(
                (int(row.get("step", 0)), finite({_key(k): v for k, v in row.items() if k != "step"}))
            )
    return rows


# ----------------------------------------------------------------------------- the import
def _client():
    try:
        from mlflow.entities import Metric
        from mlflow.tracking import MlflowClient
    except ImportError as exc:
        raise TrackingError("MLflow is not installed (requirements/ml.txt: run `make setup`)") from exc
    uri = tracking_uri()
    return MlflowClient(tracking_uri=uri), Metric, uri


def _imported(client, experiment_id: str) -> set[tuple[str, str]]:
    """(file name, sha256) of every run already in the experiment."""
    seen, token = set(), None
    while True:
        page = client.search_runs([experiment_id], max_results=1000, page_token=token)
        for r in page:
            tags = r.data.tags
            seen.add((tags.get("oibar.history.name", ""), tags.get("oibar.history.sha256", "")))
        token = page.token
        if not token:
            return seen


def import_files(
    files: Iterator[tuple[str, bytes]], source: str, rev: str = "", experiment: str = EXPERIMENT
) -> dict[str, int]:
    """Each (name, bytes) as one run of `experiment`; returns {"imported": n, "skipped": m}."""
    client, Metric, uri = _client()
    exp = client.get_experiment_by_name(experiment)
    exp_id = (
        exp.experiment_id
        if exp
        else client.create_experiment(experiment, artifact_location=artefact_root(uri))
    )
    seen = _imported(client, exp_id)
    counts = {"imported": 0, "skipped": 0}
    with tempfile.TemporaryDirectory(prefix="oibar-history-") as tmp:
        for name, data in files:
            sha = hashlib.sha256(data).hexdigest()
            if (name, sha) in seen:
                counts["skipped"] += 1
                continue
            fam = family(name)
            now = int(time.time() * 1000)
            metrics: list = []
            note = ""
            if name.endswith(".jsonl"):
                # a step logged twice (a resumed run): its last row
                by_step = {(k, step): v for step, row in log_rows(data) for k, v in row.items()}
                metrics = [Metric(k, v, now, step) for (k, step), v in by_step.items()]
            else:
                doc = json.loads(data)
                metrics = [Metric(k, v, now, 0) for k, v in file_metrics(name, doc).items()]
                if isinstance(doc, dict) and isinstance(doc.get("what"), str):
                    note = doc["what"]
            tags = {
                "oibar.kind": "history",
                "oibar.history.name": name,
                "oibar.history.family": fam,
                "oibar.history.source": f"{source}/{name}",
                "oibar.history.rev": rev,
                "oibar.history.sha256": sha,
            }
            if note:
                tags["mlflow.note.content"] = note[:5000]
            run = client.create_run(exp_id, run_name=Path(name).stem, tags=tags)
            rid = run.info.run_id
            for i in range(0, len(metrics), BATCH):
                client.log_batch(rid, metrics=metrics[i : i + BATCH])
            path = Path(tmp) / name
            path.write_bytes(data)
            client.log_artifact(rid, str(path))
            path.unlink()
            client.set_terminated(rid)
            seen.add((name, sha))
            counts["imported"] += 1
    return counts


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m oibar_models.history", description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    i = sub.add_parser("import", help=f"the old {HISTORY_PATH} files into MLflow's {EXPERIMENT!r} experiment")
    src = i.add_mutually_exclusive_group()
    src.add_argument(
        "--rev", default=None, help=f"the commit to read {HISTORY_PATH} at (default: the last that had it)"
    )
    src.add_argument("--dir", type=Path, default=None, help="a folder of the files instead of git history")
    i.add_argument("--repo", type=Path, default=REPO_ROOT, help="the git repository (default this one)")
    i.add_argument("--experiment", default=EXPERIMENT)
    a = ap.parse_args(argv)
    try:
        if a.dir is not None:
            files, source, rev = from_dir(a.dir), str(a.dir), ""
        else:
            if a.rev:
                rev = _git(a.repo, "rev-parse", "--verify", f"{a.rev}^{{commit}}").decode().strip()
            else:
                rev = last_rev_with_files(a.repo)
            files, source = from_git(a.repo, rev), HISTORY_PATH
        counts = import_files(files, source, rev, a.experiment)
    except (HistoryError, TrackingError, OSError, json.JSONDecodeError, UnicodeDecodeError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    where = f"{source} at {rev[:12]}" if rev else source
    print(
        f"{where}: {counts['imported']} imported, {counts['skipped']} already there; experiment "
        f"{a.experiment!r} in {tracking_uri()}"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
