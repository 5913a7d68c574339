"""The MCAP file under the SDK's writer, made to survive a failing disk."""

from __future__ import annotations

from pathlib import Path
from typing import IO


class GuardedFile:
    """The MCAP file as the SDK's writer sees it. A write that fails (disk full, device gone)
    is recorded once and swallowed, and every later one discarded: the SDK's writer would
    otherwise fail for good and complain on every message, and the navigator must not hear of it."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self._fh: IO[bytes] = open(path, "wb")  # noqa: SIM115  (closed by close())
        self._pos = 0
        self.error: str | None = None

    def write(self, data: bytes | bytearray) -> int:
        n = len(data)
        if self.error is None:
            try:
                self._fh.write(data)
            except OSError as exc:
                self.error = f"{self.path}: logging stopped ({exc.strerror or exc})"
        self._pos += n
        return n

    def seek(self, offset: int, whence: int = 0) -> int:
        if self.error is None:
            try:
                self._pos = self._fh.seek(offset, whence)
                return self._pos
            except OSError as exc:
                self.error = f"{self.path}: logging stopped ({exc.strerror or exc})"
        if whence == 0:
            self._pos = offset
        elif whence == 1:
            self._pos += offset
        return self._pos

    def flush(self) -> None:
        if self.error is None:
            try:
                self._fh.flush()
            except OSError as exc:
                self.error = f"{self.path}: logging stopped ({exc.strerror or exc})"

    def close(self) -> None:
        try:
            self._fh.close()
        except OSError as exc:
            if self.error is None:
                self.error = f"{self.path}: logging stopped ({exc.strerror or exc})"
