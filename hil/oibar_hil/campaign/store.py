"""The campaign folder (default build/campaigns/<name>/):

    campaign.json            the resolved dispersion model (what ``replay`` and a resume read),
                             the code it flies (``code``) and any allowed change (``code_changes``)
    parts/mission_NNNNNN.parquet   one row per finished mission, written the moment it finishes
    missions.parquet         every row in index order (``report`` writes it from the parts and
                             the table already there)
    report.md, figures/      the report
    replay/NNNNNN/           a replayed mission's rig report

A part is written to a temporary name and renamed into place, so a part either exists whole or
not at all: a campaign stopped at any moment (Ctrl-C, a lost machine, the end of a session)
resumes with the missions that have no part, and a mission finished twice (a task retried after
its worker died after all) lands in the same file name, once.

A campaign flies one version of the code: ``open_campaign`` records the fingerprint of what
flies (``fingerprint.code_fingerprint``) when it makes the folder and refuses a resume from a
checkout whose fingerprint differs (``CodeChangedError``), unless it is given the reason to
accept it, which it appends to ``code_changes``. Every row carries the short hash of the code
its worker flew (``code_sha``); a worker's other code kept with that reason is appended to
``worker_code`` (``record_worker_code``) before its rows are written.

A campaign travels as its merged table: ``pack`` writes campaign.json and missions.parquet
(zstd) to another folder, the form a session commits. A folder with a missions.parquet and
fewer parts (or none) counts every row of the table as finished; new parts are written beside
it and ``read_rows`` merges both (a mission in both must agree: it is one mission, kept once).
A table that cannot be read, or whose rows are another campaign's (name, seed, model identity)
or were flown by code campaign.json never recorded, is refused (``CampaignTableError``).
"""

from __future__ import annotations

import fcntl
import json
import math
import os
import re
import shutil
import time
from collections import Counter
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from oibar_hil.campaign import fingerprint
from oibar_hil.campaign.dispersion import CampaignConfig, config_from_dict
from oibar_hil.campaign.mission import VOLATILE_COLUMNS, column_types

PART_RE = re.compile(r"^mission_(\d{6,})\.parquet$")
CONFIG_FILE = "campaign.json"
TABLE_FILE = "missions.parquet"
TABLE_COMPRESSION = "zstd"  # 1000 rows in a few hundred kB: small enough to commit
CODE_KEYS = ("code", "code_changes", "code_adopted", "worker_code")  # campaign.json's record of what flies


class CampaignFolderError(RuntimeError):
    """The folder holds another campaign, is locked by a running one, or is not a campaign."""


class CampaignTableError(CampaignFolderError):
    """The folder's missions.parquet cannot be read, holds another campaign's rows or rows of
    code campaign.json does not record, or disagrees with a part of the same mission."""


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
    finished = len(read_rows(folder))  # a bad missions.parquet is refused before anything is recorded
    data = json.loads(path.read_text())
    code = {k: data[k] for k in CODE_KEYS if k in data}
    check = CodeCheck(now, "same")
    before = current_code(code)
    if before is None:  # made before fingerprints: what flies from now on is this checkout
        code["code"] = {**now, "time": _now()}
        code["code_adopted"] = {"time": _now(), "missions_before": finished}
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
                "missions_before": finished,
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


def record_worker_code(
    folder: Path, fp: dict[str, Any], worker: str, index: int, reason: str, changed: list[str]
) -> None:
    """Append the fingerprint of a worker's code that is not the campaign's, kept with
    ``reason``, to campaign.json's ``worker_code`` (once per fingerprint): its rows are known
    code then (``known_code``), and the report says who flew them."""
    path = Path(folder) / CONFIG_FILE
    data = json.loads(path.read_text())
    entries = data.setdefault("worker_code", [])
    if any(e.get("code", {}).get("sha256") == fp["sha256"] for e in entries):
        return
    entries.append(
        {
            "time": _now(),
            "reason": reason,
            "worker": worker,
            "first_mission": index,
            "changed": changed,
            "code": fp,
        }
    )
    _write_json(path, data)


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


def part_indices(folder: Path) -> set[int]:
    """The missions with a part in ``folder/parts``."""
    out = set()
    for p in (Path(folder) / "parts").glob("mission_*.parquet"):
        m = PART_RE.match(p.name)
        if m:
            out.add(int(m.group(1)))
    return out


def done_indices(folder: Path) -> set[int]:
    """The finished missions: those with a part and every row of missions.parquet."""
    return part_indices(folder) | {int(r["index"]) for r in table_rows(folder)}


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
    """Every finished mission's row, in index order: the parts and missions.parquet merged. A
    mission in both is one mission (a table written from the parts, or packed from a folder
    that held them): the two rows must agree in every column but the wall-clock ones
    (``VOLATILE_COLUMNS``), else ``CampaignTableError``; the table's row is kept."""
    folder = Path(folder)
    table = table_rows(folder)
    return merge_rows(table, _part_rows(folder), folder / TABLE_FILE, folder / "parts")


def _part_rows(folder: Path) -> list[dict[str, Any]]:
    import pyarrow as pa  # type: ignore[import-untyped]
    import pyarrow.parquet as pq  # type: ignore[import-untyped]

    paths = sorted((Path(folder) / "parts").glob("mission_*.parquet"))
    if not paths:
        return []
    schema = _schema()
    tables = [_conform(pq.read_table(p), schema) for p in paths]
    return pa.concat_tables(tables).to_pylist()


def _same(a: Any, b: Any) -> bool:
    if isinstance(a, float) and isinstance(b, float) and math.isnan(a) and math.isnan(b):
        return True
    return bool(a == b)


def row_differences(a: dict[str, Any], b: dict[str, Any]) -> list[str]:
    """The columns in which two rows of one mission differ, but the wall-clock ones."""
    return [k for k in a if k in b and k not in VOLATILE_COLUMNS and not _same(a[k], b[k])]


def merge_rows(
    first: list[dict[str, Any]], second: list[dict[str, Any]], first_from: Path, second_from: Path
) -> list[dict[str, Any]]:
    """Two sets of finished rows of one campaign as one, in index order; a mission in both
    must agree (``row_differences``) and is kept once, from ``first``."""
    by_index = {int(r["index"]): r for r in first}
    for r in second:
        i = int(r["index"])
        kept = by_index.get(i)
        if kept is None:
            by_index[i] = r
            continue
        diff = row_differences(kept, r)
        if diff:
            shown = ", ".join(f"{k} ({kept[k]!r} vs {r[k]!r})" for k in diff[:4])
            raise CampaignTableError(
                f"mission {i} is in both {first_from} and {second_from} and they differ in "
                f"{len(diff)} column(s): {shown}{', ...' if len(diff) > 4 else ''}; one mission "
                "flown twice with different results: keep one (remove the other) and find out why"
            )
    return [by_index[i] for i in sorted(by_index)]


def index_ranges(indices: Iterable[int]) -> str:
    """0-4, 7, 9-10."""
    spans: list[list[int]] = []
    for i in sorted(set(indices)):
        if spans and spans[-1][1] == i - 1:
            spans[-1][1] = i
        else:
            spans.append([i, i])
    return ", ".join(f"{a}" if a == b else f"{a}-{b}" for a, b in spans)


def table_rows(folder: Path) -> list[dict[str, Any]]:
    """The rows of ``folder/missions.parquet`` (none when there is none), in the table's schema,
    checked against the folder's campaign.json (``check_rows``). A file that is not a readable
    Parquet table of missions is refused (``CampaignTableError``)."""
    import pyarrow as pa  # type: ignore[import-untyped]
    import pyarrow.parquet as pq  # type: ignore[import-untyped]

    folder = Path(folder)
    path = folder / TABLE_FILE
    if not path.exists():
        return []
    try:
        table = pq.read_table(path)
        if "index" not in table.column_names:
            raise ValueError("it has no index column")
        rows = _conform(table, _schema()).to_pylist()
    except (OSError, ValueError, pa.ArrowException) as exc:
        why = (str(exc).strip().splitlines() or [type(exc).__name__])[0][:200]
        raise CampaignTableError(
            f"{path} is not a readable table of missions ({why}): restore it (from git, or pack "
            "the folder that flew them again); nothing was flown or written"
        ) from None
    check_rows(folder, rows, path)
    return rows


def known_code(record: dict[str, Any]) -> set[str]:
    """The short hashes of every code version campaign.json records (the first, each change's
    old and new one, each worker's kept other code), and "" (rows flown before campaigns
    recorded a fingerprint)."""
    shorts = {""}
    if record.get("code"):
        shorts.add(str(record["code"].get("short", "")))
    for change in record.get("code_changes") or []:
        for side in ("old", "new"):
            shorts.add(str((change.get(side) or {}).get("short", "")))
    for kept in record.get("worker_code") or []:
        shorts.add(str((kept.get("code") or {}).get("short", "")))
    return shorts


def check_rows(folder: Path, rows: list[dict[str, Any]], where: Path) -> None:
    """Rows (read from ``where``) that belong to the campaign of ``folder/campaign.json``: its
    name, seed and model identity, code it records (``known_code``), each mission once."""
    cfg = load_config(folder)
    identity = cfg.identity()
    theirs = (cfg.name, cfg.seed, identity)
    other = [r for r in rows if (r["campaign"], r["campaign_seed"], r["config_id"]) != theirs]
    if other:
        r = other[0]
        raise CampaignTableError(
            f"{where} holds another campaign's missions: {len(other)} of {len(rows)} rows (mission "
            f"{r['index']}: campaign {r['campaign']!r}, seed {r['campaign_seed']}, model "
            f"{r['config_id'] or '?'}) are not campaign {cfg.name!r} (seed {cfg.seed}, model "
            f"{identity}) of {Path(folder) / CONFIG_FILE}: put the table beside its own "
            "campaign.json (pack that campaign's folder)"
        )
    twice = sorted(i for i, n in Counter(int(r["index"]) for r in rows).items() if n > 1)
    negative = sorted(int(r["index"]) for r in rows if int(r["index"]) < 0)
    if twice or negative:
        raise CampaignTableError(
            f"{where} is not a campaign's table: "
            + (f"missions {index_ranges(twice)} appear more than once" if twice else "")
            + ("; " if twice and negative else "")
            + (f"negative mission indices {negative[:5]}" if negative else "")
        )
    known = known_code(code_record(folder))
    unknown = Counter(r["code_sha"] for r in rows if r["code_sha"] not in known)
    if unknown:
        shas = ", ".join(f"{sha} ({n} rows)" for sha, n in unknown.most_common(3))
        raise CampaignTableError(
            f"{where} holds missions flown by code {shas} that {Path(folder) / CONFIG_FILE} does "
            f"not record (it knows {', '.join(sorted(k for k in known if k)) or 'none'}): the table "
            "and campaign.json come from different folders; pack the folder that flew them"
        )


def stored_row(folder: Path, index: int) -> dict[str, Any] | None:
    """The stored row of mission ``index``: its part as written, else missions.parquet's row."""
    import pyarrow.parquet as pq  # type: ignore[import-untyped]

    path = part_path(folder, index)
    if path.exists():
        return pq.read_table(path).to_pylist()[0]
    return next((r for r in table_rows(folder) if r["index"] == index), None)


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
    """missions.parquet: the campaign's table in index order (zstd; temporary file, rename)."""
    import pyarrow as pa  # type: ignore[import-untyped]
    import pyarrow.parquet as pq  # type: ignore[import-untyped]

    path = Path(folder) / TABLE_FILE
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    rows = sorted(rows, key=lambda r: r["index"])
    pq.write_table(pa.Table.from_pylist(rows, schema=_schema()), tmp, compression=TABLE_COMPRESSION)
    with open(tmp, "rb") as fh:
        os.fsync(fh.fileno())
    os.replace(tmp, path)
    return path


def pack(folder: Path, dest: Path) -> tuple[Path, list[dict[str, Any]]]:
    """The campaign of ``folder`` as ``dest/campaign.json`` and ``dest/missions.parquet`` (every
    finished row, index order, zstd): what a session commits so that a later one, on a fresh
    checkout, resumes it (copy ``dest`` to a campaign folder and ``run``). Only reads
    ``folder`` (a running campaign may be packed; its finished missions so far are packed).
    A ``dest`` that holds another campaign, or missions ``folder`` lacks (packing would drop
    them) or disagrees with, is refused; -> (the table's path, its rows)."""
    folder, dest = Path(folder), Path(dest)
    cfg = load_config(folder)
    rows = read_rows(folder)
    check_rows(folder, rows, folder)  # never write a table its own reader would refuse
    in_place = dest.exists() and dest.resolve() == folder.resolve()
    if not in_place and (dest / CONFIG_FILE).exists():
        there = load_config(dest)
        if there.identity() != cfg.identity() or there.name != cfg.name:
            raise CampaignFolderError(
                f"{dest} holds another campaign ({there.name!r}, seed {there.seed}, model "
                f"{there.identity()}); {folder} is {cfg.name!r} (seed {cfg.seed}, model "
                f"{cfg.identity()}): pack to another folder"
            )
        have = {int(r["index"]) for r in rows}
        old = read_rows(dest)
        lost = [int(r["index"]) for r in old if int(r["index"]) not in have]
        if lost:
            raise CampaignFolderError(
                f"{dest} holds {len(lost)} finished missions that {folder} lacks "
                f"({index_ranges(lost)}): packing would drop them; resume from {dest} (copy it "
                f"to the campaign folder, run, pack again) or pack to another folder"
            )
        merge_rows(old, rows, dest, folder)  # the missions in both agree
    dest.mkdir(parents=True, exist_ok=True)
    if not in_place:  # campaign.json first: a table never sits beside a record older than it
        tmp = dest / f".{CONFIG_FILE}.{os.getpid()}.tmp"
        shutil.copyfile(folder / CONFIG_FILE, tmp)
        os.replace(tmp, dest / CONFIG_FILE)
    return write_table(dest, rows), rows
