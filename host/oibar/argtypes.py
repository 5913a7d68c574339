"""argparse value types with ranges: a bad value ends in argparse's one-line usage error (exit
2) that names the option, the value and the allowed range, never in a traceback later on
(``oibar nav --rate-hz 0`` used to divide by zero in the daemon)."""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable


def number(
    lo: float | None = None,
    hi: float | None = None,
    *,
    lo_open: bool = False,
    integer: bool = False,
) -> Callable[[str], float]:
    """A finite float (or an int with ``integer``) within [lo, hi]; ``lo_open``: strictly above lo."""

    def bound_text() -> str:
        parts = []
        if lo is not None:
            parts.append(f"{'>' if lo_open else '>='} {lo:g}")
        if hi is not None:
            parts.append(f"<= {hi:g}")
        return " and ".join(parts)

    def parse(text: str) -> float:
        kind = "an integer" if integer else "a number"
        try:
            value: float = int(text, 10) if integer else float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(
                f"{text!r} is not {kind}" + (f" ({bound_text()})" if bound_text() else "")
            ) from None
        if not math.isfinite(value):
            raise argparse.ArgumentTypeError(f"{text!r} is not a finite number")
        if (lo is not None and (value <= lo if lo_open else value < lo)) or (hi is not None and value > hi):
            raise argparse.ArgumentTypeError(f"{text!r} is out of range: must be {bound_text()}")
        return value

    parse.__name__ = "integer" if integer else "number"  # argparse names the type in its messages
    return parse


def positive(hi: float | None = None) -> Callable[[str], float]:
    return number(0.0, hi, lo_open=True)


def positive_int(hi: int | None = None) -> Callable[[str], int]:
    parse = number(1, hi, integer=True)
    return parse  # type: ignore[return-value]  # ints by construction


def non_empty(what: str) -> Callable[[str], str]:
    def parse(text: str) -> str:
        if not text.strip():
            raise argparse.ArgumentTypeError(f"{what} must not be empty")
        return text

    parse.__name__ = what
    return parse
