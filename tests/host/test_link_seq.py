"""The link's sequence-number rule (oibar.link.seq), shared by LinkClient and LinkSession."""

import pytest

from oibar.link.seq import SEQ_MAX, STALE_SEQ_WINDOW, follow_peer_seq, next_seq
from oibar.link.session import LinkSession


def follow(seqs, last=None):
    lost = 0
    for s in seqs:
        last, n = follow_peer_seq(last, s)
        lost += n
    return last, lost


def test_next_seq_wraps_past_zero():
    assert next_seq(0) == 1 and next_seq(41) == 42
    assert next_seq(SEQ_MAX) == 1  # 0 means "none" and is never sent


@pytest.mark.parametrize(
    "seqs,last,lost",
    [
        ((1, 2, 3), 3, 0),
        ((1, 2, 5), 5, 2),  # 3 and 4 never arrived
        ((SEQ_MAX - 1, SEQ_MAX, 1, 2), 2, 0),  # the wrap is not a loss
        ((SEQ_MAX - 1, 2), 2, 2),  # SEQ_MAX and 1 lost across the wrap
        ((10, 11, 0, 12), 12, 0),  # seq 0: no seq, ignored
        ((10, 11, 9, 12), 12, 0),  # 9 again: a re-send, not news
        ((10, 11, 11, 12), 12, 0),  # the same packet twice
        ((50_000, 1, 2), 2, 0),  # far behind: the peer restarted
        ((5_000, 5_000 - STALE_SEQ_WINDOW, 5_001), 5_001, 0),  # at the edge of the window: a re-send
    ],
)
def test_follow_peer_seq(seqs, last, lost):
    assert follow(seqs) == (last, lost)


class _NullWire:
    def write(self, data):
        pass

    def read(self):
        return b""


def test_link_session_counts_with_the_shared_rule():
    """LinkSession used to count the wrap from SEQ_MAX to 1 as one lost packet."""
    s = LinkSession(_NullWire(), host_version="test")
    for seq in (SEQ_MAX - 1, SEQ_MAX, 1, 2, 5):
        s._track_peer_seq(seq)
    assert s.counters.lost_peer_packets == 2
