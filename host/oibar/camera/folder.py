"""A folder of frames as a camera source: the files in natural order, their capture times from the
folder's poses/frames table when it has one (the dataset's layout), else index / rate."""

from __future__ import annotations

import csv
import os
import re
from pathlib import Path

import numpy as np

from oibar.camera.errors import (
    CameraError,
    CorruptFrame,
    EmptySource,
    EndOfStream,
    SourceNotFound,
    SourceUnreadable,
)
from oibar.camera.sources import (
    DEFAULT_RATE_HZ,
    IMAGE_EXTENSIONS,
    TIMESTAMP_TABLES,
    CameraSource,
    _cv2,
    _Pacer,
    to_rgb,
)


def _natural_key(name: str) -> list:
    return [int(part) if part.isdigit() else part.lower() for part in re.split(r"(\d+)", name)]


def _read_time_table(table: Path) -> dict[str, float]:
    """``file`` (basename, or a relative path whose basename is used) -> ``time_s``."""
    try:
        with open(table, newline="") as fh:
            reader = csv.DictReader(fh)
            cols = reader.fieldnames or []
            if "file" not in cols or "time_s" not in cols:
                raise SourceUnreadable(
                    f"timestamp table {table} needs the columns 'file' and 'time_s' (has {cols})"
                )
            times: dict[str, float] = {}
            for line, row in enumerate(reader, start=2):
                try:
                    times[os.path.basename(row["file"])] = float(row["time_s"])
                except (TypeError, ValueError) as exc:
                    raise SourceUnreadable(f"{table}, line {line}: bad time_s {row.get('time_s')!r}") from exc
            return times
    except OSError as exc:
        raise SourceUnreadable(f"cannot read timestamp table {table}: {exc}") from exc
    except UnicodeDecodeError as exc:
        raise SourceUnreadable(f"timestamp table {table} is not text: {exc}") from exc


class FolderSource(CameraSource):
    """A folder of image files, in natural sort order (``2.png`` before ``10.png``).

    Timestamps: from ``timestamps`` (a CSV with ``file`` and ``time_s`` columns) when given;
    otherwise from ``poses.csv`` or ``frames.csv`` in the folder or its parent (the synthetic
    data set's ``seqNN/frames`` + ``seqNN/poses.csv``) when one exists; otherwise index /
    ``rate_hz``. A table must cover every image and be strictly increasing in file order.
    ``realtime=True`` paces reads along the timestamps.
    """

    def __init__(
        self,
        folder: str | os.PathLike,
        *,
        rate_hz: float = DEFAULT_RATE_HZ,
        timestamps: str | os.PathLike | None = None,
        use_table: bool = True,
        realtime: bool = False,
    ) -> None:
        super().__init__()
        if not rate_hz > 0:
            raise ValueError("rate_hz must be positive")
        self.folder = Path(folder)
        self.rate_hz = float(rate_hz)
        self.timestamps_path = Path(timestamps) if timestamps is not None else None
        self.use_table = use_table
        self.name = f"folder {self.folder}"
        self._pacer = _Pacer(realtime)
        self.files: list[Path] = []
        self.times: list[float] = []
        self.table: Path | None = None
        self._index = 0

    def _find_table(self) -> Path | None:
        if self.timestamps_path is not None:
            if not self.timestamps_path.is_file():
                raise SourceNotFound(f"timestamp table {self.timestamps_path} does not exist")
            return self.timestamps_path
        if not self.use_table:
            return None
        for base in (self.folder, self.folder.parent):
            for name in TIMESTAMP_TABLES:
                if (base / name).is_file():
                    return base / name
        return None

    def _open(self) -> None:
        if not self.folder.exists():
            raise SourceNotFound(f"frame folder {self.folder} does not exist")
        if not self.folder.is_dir():
            raise SourceUnreadable(f"{self.folder} is not a folder (a video file? use VideoFileSource)")
        try:
            entries = list(self.folder.iterdir())
        except OSError as exc:
            raise SourceUnreadable(f"cannot list frame folder {self.folder}: {exc}") from exc
        files = sorted(
            (p for p in entries if p.suffix.lower() in IMAGE_EXTENSIONS and p.is_file()),
            key=lambda p: _natural_key(p.name),
        )
        if not files:
            raise EmptySource(
                f"frame folder {self.folder} holds no image file ({', '.join(IMAGE_EXTENSIONS)})"
            )
        table = self._find_table()
        if table is None:
            times = [i / self.rate_hz for i in range(len(files))]
        else:
            by_name = _read_time_table(table)
            missing = [p.name for p in files if p.name not in by_name]
            if missing:
                raise SourceUnreadable(
                    f"timestamp table {table} has no row for {len(missing)} image(s) in {self.folder}, "
                    f"e.g. {missing[0]} (pass use_table=False to use the nominal rate)"
                )
            times = [by_name[p.name] for p in files]
            for a, b, p in zip(times, times[1:], files[1:], strict=False):
                if not b > a:
                    raise SourceUnreadable(
                        f"timestamp table {table}: time_s does not increase at {p.name} ({b} after {a})"
                    )
        self.files, self.times, self.table = files, times, table
        self._index = 0
        self._pacer.reset()

    def __len__(self) -> int:
        return len(self.files)

    def _read(self) -> tuple[np.ndarray, float]:
        if self._index >= len(self.files):
            raise EndOfStream(f"{self.name}: all {len(self.files)} frames delivered")
        path, t_s = self.files[self._index], self.times[self._index]
        self._index += 1
        cv2 = _cv2()
        img = cv2.imread(str(path), cv2.IMREAD_COLOR)
        if img is None:
            # one bad file must not end (or, reopened, restart) the sequence: skipped, counted
            raise CorruptFrame(f"cannot decode image {path} (missing, truncated or not an image)")
        try:
            rgb = to_rgb(img, str(path), bgr=True)
        except CameraError as exc:
            raise CorruptFrame(str(exc)) from exc
        self._pacer.wait(t_s)
        return rgb, t_s

    def _close(self) -> None:
        pass


# ------------------------------------------------------------------------------------------
