"""The campaign folder (default build/campaigns/<name>/):

    campaign.json            the resolved dispersion model (what ``replay`` and a resume read),
                             the code it flies (``code``) and any allowed change (``code_changes``)
    parts/mission_NNNNNN.parquet   one row per finished mission, written the moment it finishes
    missions.parquet         every row in index order (``report`` writes it from the parts)
    report.md, figures/      the report
    replay/NNNNNN/           a replayed mission's rig report

A part is written to a temporary name and renamed into place, so a part either exists whole or
not at all: a campaign stopped at any moment (Ctrl-C, a lost machine, the end of a session)
resumes with the missions that have no part, and a mission finished twice (a task retried after
its worker died after all) lands in the same file name, once.

A campaign flies one version of the code: ``open_campaign`` records the fingerprint of what
flies (``fingerprint.code_fingerprint``) when it makes the folder and refuses a resume from a
checkout whose fingerprint differs (``CodeChangedError``), unless it is given the reason to
accept it, which it appends to ``code_changes``. Every row carries the short hash (``code_sha``).
"""

from __future__ import annotations

import fcntl
import json
import os
import re
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from oibar_hil.campaign import fingerprint
from oibar_hil.campaign.dispersion import CampaignConfig, config_from_dict
from oibar_hil.campaign.mission import column_types

PART_RE = re.compile(r"^mission_(\d{6,})\.parquet$")
CONFIG_FILE = "campaign.json"
CODE_KEYS = ("code", "code_changes", "code_adopted")  # campaign.json's record of what flies


class CampaignFolderError(RuntimeError):
    """The folder holds another campaign, is locked by a running one, or is not a campaign."""


class CodeChangedError(CampaignFolderError):
    """The folder's campaign was flown by other code than this checkout's (``changed``: the
    groups that differ) and no reason to accept that was given."""

    def __init__(self, message: str, changed: list[str]) -> None:
        super().__init__(message)
        self.changed = changed


@dataclass
class CodeCheck:
    """What ``open_campaign`` found of the code: ``status`` is "new" (recorded now), "same",
    "allowed" (changed, accepted with a reason and recorded) or "adopted" (a folder made before
    fingerprints: this checkout's recorded now, the rows already there carry none)."""

    fingerprint: dict[str, Any]
    status: str
    changed: list[str] = field(default_factory=list)
    previous: dict[str, Any] | None = None

    @property
    def short(self) -> str:
        return str(self.fingerprint["short"])


def _schema() -> Any:
    import pyarrow as pa  # type: ignore[import-untyped]

    types = {"int64": pa.int64(), "float64": pa.float64(), "bool": pa.bool_(), "string": pa.string()}
    return pa.schema([(c, types[k]) for c, k in column_types().items()])


def part_path(folder: Path, index: int) -> Path:
    return Path(folder) / "parts" / f"mission_{index:06d}.parquet"


def _now() -> str:
    return time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())


def open_campaign(
    folder: Path,
    cfg: CampaignConfig,
    *,
    mcu_path: str | Path | None = None,
    model_path: str | Path | None = None,
    allow_code_change: str | None = None,
) -> CodeCheck:
    """Make the folder for ``cfg`` and record the code that flies it, or check that it already
    holds the same campaign (its identity: seed, navigation, mission and dispersion model; the
    count may grow) flown by the same code (``fingerprint.code_fingerprint`` of this checkout,
    this simulated MCU and model). Other code is refused (``CodeChangedError``) unless
    ``allow_code_change`` gives the reason, which is appended to campaign.json's ``code_changes``
    with the time and both fingerprints."""
    folder = Path(folder)
    path = folder / CONFIG_FILE
    now = fingerprint.code_fingerprint(cfg.nav, mcu_path=mcu_path, model_path=model_path)
    if not path.exists():
        (folder / "parts").mkdir(parents=True, exist_ok=True)
        _write_json(path, {**cfg.to_dict(), "identity": cfg.identity(), "code": {**now, "time": _now()}})
        return CodeCheck(now, "new")
    stored = load_config(folder)
    if stored.identity() != cfg.identity():
        raise CampaignFolderError(
            f"{folder} holds another campaign (identity {stored.identity()}, seed {stored.seed}, "
            f"nav {stored.nav}); this one is {cfg.identity()} (seed {cfg.seed}, nav {cfg.nav}): "
            "use another --out or --name"
        )
    data = json.loads(path.read_text())
    code = {k: data[k] for k in CODE_KEYS if k in data}
    check = CodeCheck(now, "same")
    before = current_code(code)
    if before is None:  # made before fingerprints: what flies from now on is this checkout
        code["code"] = {**now, "time": _now()}
        code["code_adopted"] = {"time": _now(), "missions_before": len(done_indices(folder))}
        check = CodeCheck(now, "adopted")
    elif before.get("sha256") != now["sha256"]:
        changed = fingerprint.changed_groups(before, now)
        if not allow_code_change:
            raise CodeChangedError(
                f"campaign {stored.name} in {folder} was flown by code {fingerprint.describe(before)}, "
                f"this checkout is {fingerprint.describe(now)}: {', '.join(changed) or 'the fingerprint'} "
                "changed; start a new campaign (another --name or --out) or pass "
                "--allow-code-change REASON to resume it anyway",
                changed,
            )
        code.setdefault("code_changes", []).append(
            {
                "time": _now(),
                "reason": allow_code_change,
                "changed": changed,
                "missions_before": len(done_indices(folder)),
                "old": before,
                "new": now,
            }
        )
        check = CodeCheck(now, "allowed", changed, before)
    grown = cfg.missions > stored.missions  # a longer run of the same campaign: remember the count
    if grown or check.status != "same":
        base = cfg if grown else stored
        _write_json(path, {**base.to_dict(), "identity": base.identity(), **code})
    return check


def current_code(record: dict[str, Any]) -> dict[str, Any] | None:
    """The fingerprint a campaign flies now, from campaign.json's contents (or its ``CODE_KEYS``):
    the last allowed change's new one, or the one recorded when it was made; None before
    fingerprints."""
    changes = record.get("code_changes") or []
    if changes:
        return changes[-1]["new"]
    return record.get("code")


def code_record(folder: Path) -> dict[str, Any]:
    """campaign.json's record of what flies (``CODE_KEYS``; empty for an older folder)."""
    path = Path(folder) / CONFIG_FILE
    if not path.exists():
        return {}
    data = json.loads(path.read_text())
    return {k: data[k] for k in CODE_KEYS if k in data}


def load_config(folder: Path) -> CampaignConfig:
    path = Path(folder) / CONFIG_FILE
    if not path.exists():
        raise CampaignFolderError(f"{folder} is not a campaign folder (no {CONFIG_FILE})")
    d = json.loads(path.read_text())
    for key in ("identity", *CODE_KEYS):
        d.pop(key, None)
    return config_from_dict(d)


def _write_json(path: Path, data: dict) -> None:
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    tmp.write_text(json.dumps(data, indent=1, sort_keys=False) + "\n")
    os.replace(tmp, path)


@contextmanager
def locked(folder: Path) -> Iterator[None]:
    """One run at a time per campaign folder (an advisory lock, freed when the process dies)."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    fh = open(folder / ".lock", "w")  # noqa: SIM115 - held open for the lock's lifetime
    try:
        try:
            fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise CampaignFolderError(f"another run is writing to {folder} (its .lock is held)") from None
        yield
    finally:
        fh.close()


def clean_temporaries(folder: Path) -> int:
    """Remove the temporary files of parts a stopped run was writing; -> how many."""
    n = 0
    for p in (Path(folder) / "parts").glob(".*.tmp"):
        p.unlink(missing_ok=True)
        n += 1
    return n


def done_indices(folder: Path) -> set[int]:
    out = set()
    for p in (Path(folder) / "parts").glob("mission_*.parquet"):
        m = PART_RE.match(p.name)
        if m:
            out.add(int(m.group(1)))
    return out


def write_part(folder: Path, row: dict[str, Any]) -> Path:
    """One finished mission, atomically (temporary file, fsync, rename)."""
    import pyarrow as pa  # type: ignore[import-untyped]
    import pyarrow.parquet as pq  # type: ignore[import-untyped]

    path = part_path(folder, int(row["index"]))
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    table = pa.Table.from_pylist([row], schema=_schema())
    pq.write_table(table, tmp)
    with open(tmp, "rb") as fh:
        os.fsync(fh.fileno())
    os.replace(tmp, path)
    return path


def read_rows(folder: Path) -> list[dict[str, Any]]:
    """Every finished mission's row, in index order."""
    import pyarrow as pa  # type: ignore[import-untyped]
    import pyarrow.parquet as pq  # type: ignore[import-untyped]

    paths = sorted((Path(folder) / "parts").glob("mission_*.parquet"))
    if not paths:
        return []
    schema = _schema()
    tables = [_conform(pq.read_table(p), schema) for p in paths]
    rows = pa.concat_tables(tables).to_pylist()
    return sorted(rows, key=lambda r: r["index"])


def _conform(table: Any, schema: Any) -> Any:
    """A part in the table's schema; a column it lacks (a part written before that column
    existed, e.g. ``code_sha``) is filled with the column's "none" ("" or null)."""
    import pyarrow as pa  # type: ignore[import-untyped]

    for f in schema:
        if f.name not in table.column_names:
            fill = "" if pa.types.is_string(f.type) else None
            table = table.append_column(f.name, pa.array([fill] * table.num_rows, type=f.type))
    return table.select(schema.names).cast(schema)


def write_table(folder: Path, rows: list[dict[str, Any]]) -> Path:
    """missions.parquet: the campaign's table in index order."""
    import pyarrow as pa  # type: ignore[import-untyped]
    import pyarrow.parquet as pq  # type: ignore[import-untyped]

    path = Path(folder) / "missions.parquet"
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    pq.write_table(pa.Table.from_pylist(rows, schema=_schema()), tmp)
    os.replace(tmp, path)
    return path
