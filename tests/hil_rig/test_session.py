"""LinkSession on a scripted clock: retransmission, timeout, link loss, MCU restart."""

import pytest

from oibar import pb
from oibar.link.errors import LinkError
from oibar.link.framing import FrameDecoder, Packet, encode_frame
from oibar.link.session import LinkSession


class Pipe:
    def __init__(self):
        self.sent = FrameDecoder()
        self.out: list[Packet] = []
        self.inbox = bytearray()

    def write(self, data):
        self.out += self.sent.feed(data)

    def read(self):
        data, self.inbox = bytes(self.inbox), bytearray()
        return data

    def reply(self, packet):
        self.inbox += encode_frame(packet)


def handshake_reply(ack_seq, seq=1):
    p = Packet(seq=seq, ack_seq=ack_seq)
    p.handshake_reply.accepted = True
    p.handshake_reply.protocol_version = pb.PROTOCOL_VERSION
    return p


def heartbeat(seq, uptime_ms):
    p = Packet(seq=seq)
    p.heartbeat.uptime_ms = uptime_ms
    return p


def test_retransmits_same_seq_by_the_session_clock_then_times_out():
    pipe = Pipe()
    s = LinkSession(pipe)
    t = 0.0
    while t < 0.85:
        s.step(t)
        t = round(t + 0.01, 2)
    hs = [p for p in pipe.out if p.WhichOneof("body") == "handshake"]
    assert len(hs) == 4 and {p.seq for p in hs} == {1}  # original + 3 retries, same seq
    assert s.counters.timeouts == 1 and s.counters.retransmissions == 3 and not s.link_up


def test_link_up_heartbeats_and_link_loss():
    pipe = Pipe()
    s = LinkSession(pipe)
    s.step(0.0)
    pipe.reply(handshake_reply(ack_seq=1))
    s.step(0.05)
    assert s.link_up
    for i in range(1, 5):  # MCU alive for 0.4 s
        pipe.reply(heartbeat(i + 1, 100 * i))
        s.step(0.05 + 0.1 * i)
    beats = [p for p in pipe.out if p.WhichOneof("body") == "heartbeat"]
    assert len(beats) >= 2
    s.step(0.45 + 1.0)  # silent for the link timeout
    assert not s.link_up and s.counters.link_losses == 1
    with pytest.raises(LinkError):  # LinkDown, or the re-handshake still outstanding
        s.command(pb.CMD_NOOP, now_s=1.5)


def test_mcu_restart_is_noticed_from_its_uptime():
    pipe = Pipe()
    s = LinkSession(pipe)
    s.step(0.0)
    pipe.reply(handshake_reply(ack_seq=1))
    s.step(0.01)
    pipe.reply(heartbeat(2, 5000))
    s.step(0.2)
    pipe.reply(heartbeat(1, 20))  # rebooted: uptime went backwards
    s.step(0.4)
    assert s.counters.link_losses == 1
    assert s.busy and s.pending.kind == "handshake"  # re-handshaking at once


def test_host_version_longer_than_the_schema_allows_is_refused():
    with pytest.raises(ValueError):
        LinkSession(Pipe(), host_version="x" * 17)
