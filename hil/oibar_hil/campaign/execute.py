"""Running a campaign's missions: on Ray (local processes by default, or an existing cluster)
or in this one process, each finished mission written to its Parquet part at once.

Ray: one task per mission, ``num_cpus=1`` (a mission is one core: the lockstep MCU process
waits on the rig, the renderer and onnxruntime get one thread each), ``max_retries`` so a task
whose worker process dies (killed, out of memory, a lost node) runs again elsewhere; an
exception inside a mission is not retried (it is a result: outcome "error"). Only this driver
writes parts, one per returned mission index, so a retried mission cannot land twice. At most
two tasks per worker are in flight, so a stopped campaign leaves few started missions behind.

A worker on another machine imports its own checkout: each worker process fingerprints the code
it flies (``worker_code``) and returns it with every row. A row whose code is not the campaign's
is not written and stops the campaign (``WorkerCodeError``) unless ``allow_code_change`` gives
the reason to keep it: then the worker's fingerprint goes into campaign.json before its rows.
"""

from __future__ import annotations

import logging
import os
import signal
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from oibar_hil.campaign import fingerprint
from oibar_hil.campaign.dispersion import CampaignConfig
from oibar_hil.campaign.mission import ENV_THREADS, run_mission
from oibar_hil.campaign.stats import rate
from oibar_hil.campaign.store import (
    CodeChangedError,
    clean_temporaries,
    code_record,
    current_code,
    done_indices,
    read_rows,
    record_worker_code,
    write_part,
)

# Tests only: each task writes "<index>.<pid>" here when it starts, so a test can kill the
# worker process that runs a given mission.
PID_DIR_ENV = "OIBAR_CAMPAIGN_PID_DIR"
# The niceness a mission runs at (``run --nice``): set in the worker, not on the driver, so Ray's
# own daemons start at normal priority (Ray gives its node 30 s to come up, which a starved
# niced raylet on a loaded machine misses) while the missions yield to everything else.
NICE_ENV = "OIBAR_CAMPAIGN_NICE"
# The key of a task's row that carries the worker's fingerprint to the driver, which takes it
# out before writing (a row, not a tuple: a driver started before this still reads the row).
WORKER_CODE_KEY = "_worker_code"


class RayStartError(RuntimeError):
    """Ray could not start or reach its cluster (the message says what to try)."""


class WorkerCodeError(CodeChangedError):
    """A mission was flown by a worker whose code is not the campaign's (a node with a stale or
    edited checkout, another simulated MCU or model) and no reason to keep it was given."""


@dataclass
class RunSummary:
    planned: int  # missions 0..planned-1
    already_done: int  # found in the folder at the start (a resume)
    finished: int = 0  # written by this run
    lost: list[tuple[int, str]] = field(default_factory=list)  # (index, why): not written, rerun later
    interrupted: bool = False
    wall_s: float = 0.0
    workers: int = 1

    @property
    def complete(self) -> bool:
        return not self.lost and not self.interrupted


class _Tally:
    """The live success rate on the progress bar."""

    def __init__(self, rows: list[dict[str, Any]]) -> None:
        self.n = len(rows)
        self.ok = sum(bool(r["success"]) for r in rows)

    def add(self, row: dict[str, Any]) -> None:
        self.n += 1
        self.ok += bool(row["success"])

    def text(self) -> str:
        if not self.n:
            return ""
        r = rate(self.ok, self.n)
        return f"success {self.ok}/{self.n} = {100 * r.rate:.1f} % (>= {100 * r.lower_bound:.1f} % at 95 %)"


# This process's fingerprints, per (source root, navigation, MCU, model, and the size and mtime of
# the MCU binary and model files): a worker imports its modules once, so it hashes its tree once,
# at its first mission, but it starts the MCU binary and opens the models afresh each mission,
# so one rebuilt under a running campaign is hashed again.
_WORKER_CODE: dict[tuple[Any, ...], dict[str, Any]] = {}


def worker_code(nav: str, mcu_path: str | None, model_path: str | None) -> dict[str, Any]:
    """The fingerprint of the code this process flies: its own checkout (``SOURCE_ROOT`` as it
    sees it), the simulated MCU and model it runs (None: its own defaults)."""
    stamp = fingerprint.loaded_files_stamp(nav, mcu_path, model_path)
    key = (str(fingerprint.SOURCE_ROOT), nav, mcu_path, model_path, stamp)
    if key not in _WORKER_CODE:
        _WORKER_CODE[key] = fingerprint.code_fingerprint(nav, mcu_path=mcu_path, model_path=model_path)
    return _WORKER_CODE[key]


def _mission_task(
    cfg: CampaignConfig, index: int, mcu_path: str | None, model_path: str | None
) -> dict[str, Any]:
    nice = int(os.environ.get(NICE_ENV, "0") or 0)
    if nice > os.getpriority(os.PRIO_PROCESS, 0):  # only ever lower the priority
        os.setpriority(os.PRIO_PROCESS, 0, nice)
    pid_dir = os.environ.get(PID_DIR_ENV)
    if pid_dir:
        Path(pid_dir, f"{index}.{os.getpid()}").touch()
    code = worker_code(cfg.nav, mcu_path, model_path)  # before the flight: a bad tree costs none
    row = run_mission(cfg, index, mcu_path=mcu_path, model_path=model_path).row
    return {**row, "code_sha": code["short"], WORKER_CODE_KEY: code}


def _check_worker_code(
    folder: Path,
    row: dict[str, Any],
    flown_by: dict[str, Any] | None,
    code: dict[str, Any],
    allow_code_change: str | None,
    kept: set[str],
    say: Callable[[str], None],
) -> None:
    """Refuse a row flown by other code than the campaign's (``WorkerCodeError``: it is not
    written, so a resume flies the mission again), or, with a reason, record the worker's
    fingerprint in campaign.json (once) so the rows it flies are known code."""
    if flown_by is not None and flown_by.get("sha256") == code["sha256"]:
        return
    if flown_by is None:  # a worker whose checkout predates worker fingerprints
        changed, theirs = ["the fingerprint, none sent"], "unknown"
    else:
        changed, theirs = fingerprint.changed_groups(code, flown_by), fingerprint.describe(flown_by)
    what = (
        f"mission {row['index']} was flown by worker {row.get('worker') or '?'} with code {theirs}, "
        f"the campaign flies {fingerprint.describe(code)} (they differ in "
        f"{', '.join(changed) or 'the fingerprint'})"
    )
    if not allow_code_change or flown_by is None:  # unknown code cannot be recorded, so not kept
        raise WorkerCodeError(
            f"{what}; its row was not written and the campaign stopped: give that node the "
            "campaign's code (checkout, simulated MCU, model) and run again to resume"
            + (", or pass --allow-code-change REASON to keep missions of other code" if flown_by else ""),
            changed,
        )
    if flown_by["sha256"] not in kept:
        kept.add(flown_by["sha256"])
        worker = str(row.get("worker", ""))
        record_worker_code(folder, flown_by, worker, int(row["index"]), allow_code_change, changed)
        say(f"{what}; kept: {allow_code_change!r} (recorded in campaign.json)")


def pending_indices(folder: Path, missions: int) -> list[int]:
    done = done_indices(folder)
    return [i for i in range(missions) if i not in done]


def run_missions(
    cfg: CampaignConfig,
    folder: Path,
    *,
    executor: str = "ray",
    workers: int | None = None,
    address: str | None = None,
    max_retries: int = 3,
    mcu_path: str | None = None,
    model_path: str | None = None,
    progress: bool = True,
    on_row: Callable[[dict[str, Any]], None] | None = None,
    code: dict[str, Any] | None = None,
    allow_code_change: str | None = None,
) -> RunSummary:
    """Run every mission 0..cfg.missions-1 not finished in ``folder`` yet (no part, no row in
    its missions.parquet: a packed campaign resumes from its table). Each row's ``code_sha`` is
    the short hash of the code its worker flew; it must be ``code``, the campaign's fingerprint
    (default: the one ``open_campaign`` checked and recorded in the folder), else the run stops
    with ``WorkerCodeError`` before writing that row, unless ``allow_code_change`` gives the
    reason to keep it."""
    folder = Path(folder)
    if code is None:
        code = current_code(code_record(folder))
    kept: set[str] = set()
    clean_temporaries(folder)
    todo = pending_indices(folder, cfg.missions)
    previous = read_rows(folder)
    summary = RunSummary(planned=cfg.missions, already_done=cfg.missions - len(todo))
    tally = _Tally([r for r in previous if r["index"] < cfg.missions])
    bar = None
    if progress and todo:
        from oibar.progress import Progress

        bar = Progress(f"campaign {cfg.name} ({cfg.nav})", total=len(todo), unit="mission")
        bar.set_postfix_str(tally.text())

    def say(text: str) -> None:
        if bar is not None:
            bar.write(text)
        else:
            print(text, file=sys.stderr)

    def finished(row: dict[str, Any]) -> None:
        row = dict(row)
        flown_by = row.pop(WORKER_CODE_KEY, None)
        if code is None:  # a folder never opened (no fingerprint): its rows say none
            row["code_sha"] = ""
        else:
            _check_worker_code(folder, row, flown_by, code, allow_code_change, kept, say)
        write_part(folder, row)
        summary.finished += 1
        tally.add(row)
        if on_row is not None:
            on_row(row)
        if bar is not None:
            bar.set_postfix_str(tally.text())
            bar.update(1)
            if row["outcome"] == "error":
                bar.write(f"mission {row['index']}: rig error: {row['error'][:200]}")

    t0 = time.perf_counter()
    try:
        if not todo:
            pass
        elif executor == "serial":
            summary.workers = 1
            _WORKER_CODE.clear()  # this process is the worker: its code now (a test edits the tree)
            nice = int(os.environ.get(NICE_ENV, "0") or 0)
            if nice > os.getpriority(os.PRIO_PROCESS, 0):
                os.setpriority(os.PRIO_PROCESS, 0, nice)
            for i in todo:
                finished(_mission_task(cfg, i, mcu_path, model_path))
        elif executor == "ray":
            _run_on_ray(cfg, todo, summary, finished, workers, address, max_retries, mcu_path, model_path)
        else:
            raise ValueError(f"unknown executor {executor!r}: ray or serial")
    except KeyboardInterrupt:
        summary.interrupted = True
    finally:
        summary.wall_s = time.perf_counter() - t0
        if bar is not None:
            bar.close()
    return summary


def _worker_env() -> dict[str, str]:
    env = dict(ENV_THREADS)
    for k, v in os.environ.items():
        if k.startswith("OIBAR_CAMPAIGN_"):
            env[k] = v
    return env


def _run_on_ray(
    cfg: CampaignConfig,
    todo: list[int],
    summary: RunSummary,
    finished: Callable[[dict[str, Any]], None],
    workers: int | None,
    address: str | None,
    max_retries: int,
    mcu_path: str | None,
    model_path: str | None,
) -> None:
    import ray

    runtime_env = {"env_vars": _worker_env()}
    try:
        if address:
            ray.init(
                address=address, runtime_env=runtime_env, log_to_driver=False, logging_level=logging.WARNING
            )
        else:
            # "local": a cluster of our own, never one somebody else started on this machine
            ray.init(
                address="local",
                num_cpus=workers or os.cpu_count() or 1,
                include_dashboard=False,
                runtime_env=runtime_env,
                log_to_driver=False,
                logging_level=logging.WARNING,
            )
    except Exception as exc:  # noqa: BLE001 - Ray raises plain Exceptions for a node that did not start
        ray.shutdown()
        where = f"the cluster at {address}" if address else "a local Ray node"
        raise RayStartError(
            f"could not start {where}: {str(exc).splitlines()[0]} (an overloaded machine: run again, "
            "do not nice the driver (use --nice), or --executor serial)"
        ) from exc
    # A stop (SIGTERM from a scheduler, nohup's kill) ends the run as Ctrl-C does: parts stay.
    previous_term = signal.signal(signal.SIGTERM, signal.default_int_handler)
    try:
        cpus = int(ray.cluster_resources().get("CPU", 1))
        summary.workers = cpus
        task = ray.remote(num_cpus=1, max_retries=max_retries, retry_exceptions=False)(_mission_task)
        cfg_ref = ray.put(cfg)
        queue = list(todo)
        inflight: dict[Any, int] = {}
        window = max(1, 2 * cpus)
        while queue or inflight:
            while queue and len(inflight) < window:
                i = queue.pop(0)
                inflight[task.remote(cfg_ref, i, mcu_path, model_path)] = i
            ready, _ = ray.wait(list(inflight), num_returns=1, timeout=2.0)
            for ref in ready:
                i = inflight.pop(ref)
                try:
                    row = ray.get(ref)
                except ray.exceptions.RayError as exc:  # its worker died more than max_retries times
                    summary.lost.append((i, f"{type(exc).__name__}: {str(exc).splitlines()[0][:300]}"))
                    continue
                finished(row)
    finally:
        signal.signal(signal.SIGTERM, previous_term)
        ray.shutdown()
