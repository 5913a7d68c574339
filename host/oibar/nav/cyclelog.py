"""The cycle log: one JSON object per navigation cycle (JSON Lines), enough to replay a run.

Line 1 is a header (``"kind": "header"``: model path and version, camera, geometry, start time,
software version); then one ``"kind": "cycle"`` line per cycle; the daemon ends with a
``"kind": "footer"`` summary. With ``frames_dir`` the frame of every cycle is written beside the
log (JPEG, ``<seq>.jpg``) and the cycle line names it, so ``oibar replay`` can re-run the
estimation on exactly what the daemon saw.

A full disk or an unwritable log never stops navigation: the writer turns itself off, keeps a
count of lost lines and reports the error once (``error``); the daemon shows it in the status
line and the footer (when it can still be written).
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np


def _jsonable(x: Any) -> Any:
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return _jsonable(x.tolist())
    if isinstance(x, (np.floating, float)):
        v = float(x)
        return v if math.isfinite(v) else None
    if isinstance(x, (np.integer,)):
        return int(x)
    if isinstance(x, (np.bool_,)):
        return bool(x)
    return x


class CycleLogError(RuntimeError):
    """A cycle log cannot be read: the message names the file and line."""


class CycleLog:
    def __init__(
        self,
        path: str | Path,
        frames_dir: str | Path | None = None,
        jpeg_quality: int = 92,
        flush_every: int = 10,
    ) -> None:
        self.path = Path(path)
        self.frames_dir = Path(frames_dir) if frames_dir else None
        self.jpeg_quality = int(jpeg_quality)
        self.flush_every = max(1, int(flush_every))
        self.lines_written = 0
        self.lines_lost = 0
        self.frames_written = 0
        self.error: str | None = None
        self.path.parent.mkdir(parents=True, exist_ok=True)
        if self.frames_dir:
            self.frames_dir.mkdir(parents=True, exist_ok=True)
        # line buffered writes would cost a syscall per cycle; flush every few cycles instead
        self._fh = open(self.path, "a", encoding="utf-8")  # noqa: SIM115  (closed by close())

    @property
    def ok(self) -> bool:
        return self.error is None

    def _fail(self, exc: OSError) -> None:
        if self.error is None:
            self.error = f"{self.path}: logging stopped ({exc.strerror or exc})"
        try:
            self._fh.close()
        except OSError:
            pass

    def write(self, record: dict[str, Any]) -> bool:
        if self.error is not None:
            self.lines_lost += 1
            return False
        try:
            self._fh.write(json.dumps(_jsonable(record), separators=(",", ":")) + "\n")
            self.lines_written += 1
            if self.lines_written % self.flush_every == 0:
                self._fh.flush()
        except OSError as exc:
            self.lines_lost += 1
            self._fail(exc)
            return False
        return True

    def save_frame(self, image: np.ndarray, seq: int) -> str | None:
        """Write one frame for replay; returns its name relative to the log's folder."""
        if self.frames_dir is None or self.error is not None:
            return None
        from PIL import Image

        path = self.frames_dir / f"{int(seq):08d}.jpg"
        tmp = path.with_suffix(".jpg.tmp")
        try:
            Image.fromarray(image).save(tmp, format="JPEG", quality=self.jpeg_quality)
            os.replace(tmp, path)
        except OSError as exc:
            self._fail(exc)
            try:
                tmp.unlink()
            except OSError:
                pass
            return None
        self.frames_written += 1
        return os.path.relpath(path, self.path.parent)

    def close(self) -> None:
        if self.error is None:
            try:
                self._fh.flush()
                self._fh.close()
            except OSError as exc:
                self._fail(exc)

    def __enter__(self) -> CycleLog:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def read_log(path: str | Path) -> Iterator[dict[str, Any]]:
    """Yield the records of a cycle log. A truncated last line (the process was killed
    mid-write) is skipped; any other bad line raises CycleLogError naming the line."""
    path = Path(path)
    if not path.is_file():
        raise CycleLogError(f"{path}: cycle log not found")
    with open(path, encoding="utf-8", errors="replace") as fh:
        lines = fh.readlines()
    for i, line in enumerate(lines, 1):
        if not line.strip():
            continue
        try:
            rec = json.loads(line)
        except json.JSONDecodeError as exc:
            if i == len(lines) and not line.endswith("\n"):
                return  # killed mid-write: everything before it is good
            raise CycleLogError(f"{path}:{i}: not a JSON object ({exc.msg})") from exc
        if not isinstance(rec, dict) or "kind" not in rec:
            raise CycleLogError(f"{path}:{i}: not a cycle-log record (no 'kind')")
        yield rec
