"""oibar.progress: a live line on a terminal; plain, time-spaced lines in a log (injected clock)."""

import io

from oibar.progress import Progress, StatusLine, progress_iter


class Clock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


class Tty(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_status_line_in_a_log_is_plain_lines_spaced_by_the_period():
    out, clock = io.StringIO(), Clock()
    s = StatusLine(out, period_s=5.0, clock=clock)
    assert not s.tty  # a StringIO is no terminal
    shown = []
    for k in range(121):  # an update every 0.1 s for 12 s
        clock.t = 100.0 + k / 10
        shown.append(s.show(f"t {k / 10:.1f} s"))
    s.end()
    text = out.getvalue()
    assert "\r" not in text and "\x1b" not in text
    lines = text.splitlines()
    # the first, then one every 5 s (t 0, 5, 10), then the newest at the end
    assert lines == ["t 0.0 s", "t 5.0 s", "t 10.0 s", "t 12.0 s"]
    assert sum(shown) == 3


def test_status_line_on_a_terminal_redraws_in_place():
    out, clock = Tty(), Clock()
    s = StatusLine(out, clock=clock)
    assert s.tty
    s.show("one")
    clock.t += 1.0
    s.show("two")
    s.end()
    text = out.getvalue()
    assert text.startswith("\rone") and "\rtwo" in text and text.endswith("\n")
    assert text.count("\n") == 1


def test_progress_in_a_log_reports_start_period_and_end():
    out, clock = io.StringIO(), Clock()
    bar = Progress("rendering", total=100, unit="frame", stream=out, period_s=5.0, clock=clock)
    for _ in range(100):
        clock.t += 0.2  # 20 s in all
        bar.update(1)
    bar.set_postfix(loss="0.25")
    bar.close()
    lines = out.getvalue().splitlines()
    assert "\r" not in out.getvalue()
    assert lines[0].startswith("rendering: 0/100 frame (0%)")
    assert lines[-1].startswith("rendering: 100/100 frame (100%) [00:20, 5 frame/s] loss=0.25")
    assert len(lines) == 1 + 4 + 1  # the start, one per 5 s, the end


def test_progress_not_left_on_a_terminal_is_wiped():
    out, clock = Tty(), Clock()
    with Progress("epoch 1/3", total=4, unit="batch", leave=False, stream=out, clock=clock) as bar:
        for _ in range(4):
            clock.t += 1.0
            bar.update(1)
    text = out.getvalue()
    assert "|#####" in text and text.endswith("\r\x1b[K") and "\n" not in text


def test_progress_iter_yields_everything_and_counts_it():
    out = io.StringIO()
    assert list(progress_iter(range(7), "predict", unit="batch", stream=out)) == list(range(7))
    assert out.getvalue().splitlines()[-1].startswith("predict: 7/7 batch (100%)")


def test_message_keeps_the_status_line_intact():
    out, clock = Tty(), Clock()
    bar = Progress("fault matrix", total=2, unit="cell", stream=out, clock=clock)
    bar.write("FAIL x@y: reason")
    bar.close()
    assert "\r\x1b[KFAIL x@y: reason\n" in out.getvalue()
