"""The old docs/data files into MLflow (oibar_models.history, issue 61 item 3): read from git
history at the last commit that had them, one run per file with its artefact, tags and metrics,
and a second import adds nothing. A temporary repository and a temporary file store (MLflow's
folder store: no database to create, so the test takes a few seconds)."""

from __future__ import annotations

import json
import subprocess

import pytest

pytest.importorskip("mlflow")

from oibar_models.history import EXPERIMENT, HistoryError, family, last_rev_with_files, main  # noqa: E402

EVAL = {
    "test": {
        "oibarnet 0.34.0": {
            "seq01": {"frames": 1760, "dt_mean_pct": 0.25, "dq_mean_deg": 0.33, "_bins": [{"bin": "0-1 m"}]}
        }
    }
}
LOG = [{"step": 1000, "train_loss": 3.0, "val_dt_mean_pct": 0.5}, {"step": 2000, "train_loss": 2.0}]
JUDGE = {"part": "4 (loop)", "holds": True, "clauses": []}


def _git(repo, *args) -> str:
    cmd = ["git", "-C", str(repo), "-c", "user.name=t", "-c", "user.email=t@example.org", *args]
    return subprocess.run(cmd, check=True, capture_output=True, text=True).stdout.strip()


@pytest.fixture()
def repo(tmp_path):
    """A repository whose second commit removed docs/data (as the commit that moved it out did)."""
    r = tmp_path / "repo"
    data = r / "docs" / "data"
    data.mkdir(parents=True)
    (data / "eval_test_0340.json").write_text(json.dumps(EVAL))
    (data / "kp_train_stage15_log.jsonl").write_text("".join(json.dumps(x) + "\n" for x in LOG))
    (data / "judge_0340_part4.json").write_text(json.dumps(JUDGE))
    (data / "notes.txt").write_text("not a record\n")
    (r / "README.md").write_text("x\n")
    _git(r, "init", "-q")
    _git(r, "add", ".")
    _git(r, "commit", "-q", "-m", "records")
    had = _git(r, "rev-parse", "HEAD")
    _git(r, "rm", "-q", "-r", "docs/data")
    _git(r, "commit", "-q", "-m", "moved out")
    return r, had


@pytest.fixture()
def store(tmp_path, monkeypatch):
    monkeypatch.setenv("MLFLOW_ALLOW_FILE_STORE", "true")
    uri = (tmp_path / "mlruns").as_uri()
    monkeypatch.setenv("MLFLOW_TRACKING_URI", uri)
    from mlflow.tracking import MlflowClient

    # the URI given, not MLflow's process-wide one: an earlier test (a build) may have set that
    return MlflowClient(tracking_uri=uri)


def _runs(client) -> dict:
    exp = client.get_experiment_by_name(EXPERIMENT)
    return {r.data.tags["oibar.history.name"]: r for r in client.search_runs([exp.experiment_id])}


def test_the_files_of_the_last_commit_that_had_them_become_runs(repo, store, capsys):
    r, had = repo
    assert last_rev_with_files(r) == had
    assert main(["import", "--repo", str(r)]) == 0
    runs = _runs(store)
    assert set(runs) == {"eval_test_0340.json", "kp_train_stage15_log.jsonl", "judge_0340_part4.json"}
    ev = runs["eval_test_0340.json"]
    assert ev.data.tags["oibar.history.rev"] == had
    assert ev.data.tags["oibar.history.source"] == "docs/data/eval_test_0340.json"
    assert ev.data.metrics["test/oibarnet 0.34.0/seq01/dt_mean_pct"] == 0.25
    assert not any("_bins" in k for k in ev.data.metrics)
    assert [a.path for a in store.list_artifacts(ev.info.run_id)] == ["eval_test_0340.json"]
    assert runs["judge_0340_part4.json"].data.metrics["holds"] == 1.0
    log = runs["kp_train_stage15_log.jsonl"]
    assert [(m.step, m.value) for m in store.get_metric_history(log.info.run_id, "train_loss")] == [
        (1000, 3.0),
        (2000, 2.0),
    ]
    assert "3 imported, 0 already there" in capsys.readouterr().out

    # again, from the same commit named, and from a folder of the same files: nothing new
    assert main(["import", "--repo", str(r), "--rev", had[:8]]) == 0
    assert "0 imported, 3 already there" in capsys.readouterr().out
    folder = r / "copy"
    folder.mkdir()
    (folder / "judge_0340_part4.json").write_text(json.dumps(JUDGE))
    (folder / "probe_val_0340.json").write_text(json.dumps({"rows": []}))
    assert main(["import", "--dir", str(folder)]) == 0
    assert "1 imported, 1 already there" in capsys.readouterr().out
    assert len(_runs(store)) == 4


def test_a_commit_without_the_files_is_refused(repo, store, capsys):
    r, _ = repo
    assert main(["import", "--repo", str(r), "--rev", "HEAD"]) == 2
    assert "no JSON files under docs/data" in capsys.readouterr().err
    assert main(["import", "--repo", str(r), "--rev", "nosuchrev"]) == 2
    empty = r.parent / "empty"
    empty.mkdir()
    _git(empty, "init", "-q")
    _git(empty, "commit", "-q", "--allow-empty", "-m", "nothing")
    with pytest.raises(HistoryError, match="no commit"):
        last_rev_with_files(empty)


def test_family():
    assert family("kp_train_stage15_log.jsonl") == "train_log"
    assert family("probe_val_0340.json") == "probe"
    assert family("fuzz_dispatch_campaign.json") == "other"
