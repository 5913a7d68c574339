"""The flight log's one error."""

from __future__ import annotations


class FlightLogError(RuntimeError):
    """A flight log that cannot be read: the message names the file and why."""
