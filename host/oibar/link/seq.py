"""Sequence numbers of the link (docs/link.md): one rule for every host-side implementation.

Each side numbers its packets 1..SEQ_MAX and wraps to 1 (0 means "none"). The receiver follows
the peer's numbering to count packets it never saw; a packet a little behind the last one is a
re-send (the MCU answers a retransmitted request from its duplicate cache), not news.
"""

from __future__ import annotations

SEQ_MAX = 0xFFFFFFFF
# How far behind the last seen seq a packet may be and still count as a re-send rather than
# the peer starting its numbering again.
STALE_SEQ_WINDOW = 1024


def next_seq(seq: int) -> int:
    """The seq after ``seq``: SEQ_MAX wraps to 1."""
    return seq % SEQ_MAX + 1


def follow_peer_seq(last: int | None, seq: int) -> tuple[int | None, int]:
    """The peer sent ``seq`` after ``last`` (None: nothing yet). Returns the seq to remember and
    how many of the peer's packets went missing in between."""
    if seq == 0:
        return last, 0  # no seq on this packet
    if last is None:
        return seq, 0
    ahead = (seq - next_seq(last)) % SEQ_MAX  # packets skipped, across the wrap
    behind = (last - seq) % SEQ_MAX
    if seq == last or behind <= STALE_SEQ_WINDOW:
        return last, 0  # a re-send: nothing new about the numbering
    if ahead < SEQ_MAX // 2:
        return seq, ahead
    return seq, 0  # far behind: the peer restarted its numbering
