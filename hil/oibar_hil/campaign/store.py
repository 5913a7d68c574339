"""The campaign folder (default build/campaigns/<name>/):

    campaign.json            the resolved dispersion model (what ``replay`` and a resume read)
    parts/mission_NNNNNN.parquet   one row per finished mission, written the moment it finishes
    missions.parquet         every row in index order (``report`` writes it from the parts)
    report.md, figures/      the report
    replay/NNNNNN/           a replayed mission's rig report

A part is written to a temporary name and renamed into place, so a part either exists whole or
not at all: a campaign stopped at any moment (Ctrl-C, a lost machine, the end of a session)
resumes with the missions that have no part, and a mission finished twice (a task retried after
its worker died after all) lands in the same file name, once.
"""

from __future__ import annotations

import fcntl
import json
import os
import re
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from oibar_hil.campaign.dispersion import CampaignConfig, config_from_dict
from oibar_hil.campaign.mission import column_types

PART_RE = re.compile(r"^mission_(\d{6,})\.parquet$")
CONFIG_FILE = "campaign.json"


class CampaignFolderError(RuntimeError):
    """The folder holds another campaign, is locked by a running one, or is not a campaign."""


def _schema() -> Any:
    import pyarrow as pa  # type: ignore[import-untyped]

    types = {"int64": pa.int64(), "float64": pa.float64(), "bool": pa.bool_(), "string": pa.string()}
    return pa.schema([(c, types[k]) for c, k in column_types().items()])


def part_path(folder: Path, index: int) -> Path:
    return Path(folder) / "parts" / f"mission_{index:06d}.parquet"


def open_campaign(folder: Path, cfg: CampaignConfig) -> None:
    """Make the folder for ``cfg``, or check that it already holds the same campaign (its
    identity: seed, navigation, mission and dispersion model; the count may grow)."""
    folder = Path(folder)
    path = folder / CONFIG_FILE
    if path.exists():
        stored = load_config(folder)
        if stored.identity() != cfg.identity():
            raise CampaignFolderError(
                f"{folder} holds another campaign (identity {stored.identity()}, seed {stored.seed}, "
                f"nav {stored.nav}); this one is {cfg.identity()} (seed {cfg.seed}, nav {cfg.nav}): "
                "use another --out or --name"
            )
        if cfg.missions > stored.missions:  # a longer run of the same campaign: remember the count
            _write_json(path, {**cfg.to_dict(), "identity": cfg.identity()})
        return
    (folder / "parts").mkdir(parents=True, exist_ok=True)
    _write_json(path, {**cfg.to_dict(), "identity": cfg.identity()})


def load_config(folder: Path) -> CampaignConfig:
    path = Path(folder) / CONFIG_FILE
    if not path.exists():
        raise CampaignFolderError(f"{folder} is not a campaign folder (no {CONFIG_FILE})")
    d = json.loads(path.read_text())
    d.pop("identity", None)
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
    tables = [pq.read_table(p).select(schema.names).cast(schema) for p in paths]
    rows = pa.concat_tables(tables).to_pylist()
    return sorted(rows, key=lambda r: r["index"])


def write_table(folder: Path, rows: list[dict[str, Any]]) -> Path:
    """missions.parquet: the campaign's table in index order."""
    import pyarrow as pa  # type: ignore[import-untyped]
    import pyarrow.parquet as pq  # type: ignore[import-untyped]

    path = Path(folder) / "missions.parquet"
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    pq.write_table(pa.Table.from_pylist(rows, schema=_schema()), tmp)
    os.replace(tmp, path)
    return path
