"""Progress on stderr: a live line on a terminal, plain lines every few seconds elsewhere.

On a terminal the line is redrawn in place (carriage return, cut to the terminal's width). When
the output is a file, a pipe or CI's log, a carriage-return line per update would fill the log
with thousands of lines nobody reads; there the same text goes out as an ordinary line at most
once every ``period_s`` seconds of wall time (default 5 s), plus the first and the last.

Two helpers, used by the rig and the demo, the data-set writer, the training loops and the
command-line tools:

    status = StatusLine()                       # free text: oibar nav's status line
    status.show(f"t {t:.1f} s  range {r:.2f} m")
    status.end()

    with Progress("rendering", total=n, unit="frame") as bar:   # counted work (tqdm's subset)
        for ...:
            bar.update(1)

The time comes from ``clock`` (default ``time.monotonic``), so a test drives it by hand.
"""

from __future__ import annotations

import shutil
import sys
import time
from collections.abc import Callable, Iterable, Iterator, Sized
from typing import TextIO, TypeVar

__all__ = ["DEFAULT_PERIOD_S", "Progress", "StatusLine", "progress_iter"]

DEFAULT_PERIOD_S = 5.0  # plain lines at most this often when not on a terminal
LIVE_PERIOD_S = 0.1  # redraws at most this often on a terminal

T = TypeVar("T")


class StatusLine:
    """One line of status text: redrawn in place on a terminal, a plain line every ``period_s``
    otherwise. ``show`` returns whether it wrote."""

    def __init__(
        self,
        stream: TextIO | None = None,
        *,
        period_s: float = DEFAULT_PERIOD_S,
        live_period_s: float = LIVE_PERIOD_S,
        tty: bool | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.stream = stream if stream is not None else sys.stderr
        if tty is None:
            isatty = getattr(self.stream, "isatty", None)
            tty = bool(isatty()) if isatty is not None else False
        self.tty = tty
        self.period_s = period_s
        self.live_period_s = live_period_s
        self.clock = clock
        self._last_s: float | None = None
        self._pending = ""  # the newest text not written yet (non-terminal)
        self._open = False  # a live line is on screen without its newline

    def show(self, text: str, *, force: bool = False) -> bool:
        now = self.clock()
        wait_s = self.live_period_s if self.tty else self.period_s
        if not force and self._last_s is not None and now - self._last_s < wait_s:
            self._pending = text
            return False
        self._write(text)
        self._last_s = now
        self._pending = ""
        return True

    def _write(self, text: str) -> None:
        if self.tty:
            width = max(20, shutil.get_terminal_size().columns - 1)  # a wrapped line cannot be redrawn
            self.stream.write("\r" + text[:width] + "\x1b[K")
            self._open = True
        else:
            self.stream.write(text + "\n")
        self.stream.flush()

    def message(self, text: str) -> None:
        """A line of its own (a warning, a result) that does not disturb the status line."""
        if self._open:
            self.stream.write("\r\x1b[K")
        self.stream.write(text + "\n")
        self.stream.flush()
        self._open = False

    def clear(self) -> None:
        """Take a live line off the screen (a terminal only; a log keeps its lines)."""
        if self._open:
            self.stream.write("\r\x1b[K")
            self.stream.flush()
        self._open = False
        self._pending = ""

    def end(self, text: str | None = None) -> None:
        """Write ``text`` (or the newest text not shown yet) and finish the line."""
        final = text if text is not None else self._pending
        if final:
            self._write(final)
        if self.tty and self._open:
            self.stream.write("\n")
            self.stream.flush()
        self._open = False
        self._pending = ""


def _duration(seconds: float) -> str:
    m, s = divmod(int(seconds), 60)
    h, m = divmod(m, 60)
    return f"{h}:{m:02d}:{s:02d}" if h else f"{m:02d}:{s:02d}"


class Progress:
    """Counted work (the part of tqdm's interface this project uses: ``update``, ``n``,
    ``set_description``, ``set_postfix``, ``set_postfix_str``, ``write``, ``close``). On a terminal
    a bar (``leave=False``: wiped at ``close``); elsewhere ``desc: n/total unit (pct) [elapsed,
    rate]`` at the start, every ``period_s`` and at ``close``."""

    BAR_WIDTH = 20

    def __init__(
        self,
        desc: str = "",
        total: float | None = None,
        unit: str = "it",
        *,
        leave: bool = True,
        stream: TextIO | None = None,
        period_s: float = DEFAULT_PERIOD_S,
        tty: bool | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.desc = desc
        self.total = total
        self.unit = unit
        self.leave = leave
        self.n: float = 0
        self.postfix = ""
        self.clock = clock
        self.line = StatusLine(stream, period_s=period_s, tty=tty, clock=clock)
        self._t0 = clock()
        self._closed = False
        self.line.show(self.text(), force=True)

    def __enter__(self) -> Progress:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def text(self) -> str:
        elapsed = self.clock() - self._t0
        rate = self.n / elapsed if elapsed > 0 else 0.0
        count = f"{self.n:g}/{self.total:g}" if self.total else f"{self.n:g}"
        pct = f"{100.0 * self.n / self.total:3.0f}%" if self.total else ""
        head = f"{self.desc}: " if self.desc else ""
        tail = f" [{_duration(elapsed)}, {rate:.3g} {self.unit}/s]" + (
            f" {self.postfix}" if self.postfix else ""
        )
        if self.line.tty and self.total:
            done = int(self.BAR_WIDTH * min(1.0, self.n / self.total))
            bar = "#" * done + "-" * (self.BAR_WIDTH - done)
            return f"{head}{pct} |{bar}| {count} {self.unit}{tail}"
        return f"{head}{count} {self.unit}" + (f" ({pct.strip()})" if pct else "") + tail

    def update(self, n: float = 1) -> None:
        self.n += n
        self.line.show(self.text())

    def set_description(self, desc: str) -> None:
        self.desc = desc

    def set_postfix_str(self, text: str) -> None:
        self.postfix = text

    def set_postfix(self, **values: object) -> None:
        self.postfix = ", ".join(f"{k}={v}" for k, v in values.items())

    def write(self, text: str) -> None:
        self.line.message(text)

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        if self.line.tty and not self.leave:
            self.line.clear()
        else:  # a log always gets the final count
            self.line.end(self.text())


def progress_iter(
    items: Iterable[T],
    desc: str = "",
    total: float | None = None,
    unit: str = "it",
    *,
    leave: bool = True,
    stream: TextIO | None = None,
    period_s: float = DEFAULT_PERIOD_S,
    tty: bool | None = None,
    clock: Callable[[], float] = time.monotonic,
) -> Iterator[T]:
    """``for x in progress_iter(xs, "predict", unit="batch")``: a :class:`Progress` over an
    iterable (``total`` from ``len(items)`` when it has one)."""
    if total is None and isinstance(items, Sized):
        total = len(items)
    bar = Progress(desc, total, unit, leave=leave, stream=stream, period_s=period_s, tty=tty, clock=clock)
    try:
        for x in items:
            yield x
            bar.update(1)
    finally:
        bar.close()
