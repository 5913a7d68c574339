"""The link core (oibar.link.core) on a scripted clock: the rules LinkClient and the rig's
LinkSession share, checked once here without threads or ports."""

from oibar import pb
from oibar.link.core import LinkCore
from oibar.link.framing import FrameDecoder, Packet, encode_frame


def sent(core):
    out = []
    dec = FrameDecoder()
    for frame in core.take_output():
        out += dec.feed(frame)
    return out


def reply_handshake(core, now_s, uptime_ms=1000):
    hs = [p for p in sent(core) if p.WhichOneof("body") == "handshake"]
    assert hs, "a handshake was sent"
    p = Packet(seq=1, ack_seq=hs[-1].seq)
    p.handshake_reply.accepted = True
    p.handshake_reply.protocol_version = pb.PROTOCOL_VERSION
    p.handshake_reply.uptime_ms = uptime_ms
    core.receive(encode_frame(p), now_s)
    assert core.link_up


def telemetry(seq, uptime_ms, host_link_alive=True):
    p = Packet(seq=seq)
    p.telemetry.uptime_ms = uptime_ms
    p.telemetry.host_link_alive = host_link_alive
    return encode_frame(p)


def test_telemetry_saying_the_host_link_is_down_means_a_restart_and_a_new_handshake():
    core = LinkCore()
    core.step(0.0)
    reply_handshake(core, 0.01)
    core.receive(telemetry(2, 1100), 0.1)
    assert core.link_up
    core.receive(telemetry(3, 1200, host_link_alive=False), 0.2)
    assert not core.link_up and core.counters.mcu_restarts == 1
    core.step(0.2)
    assert core.busy and core.pending.kind == "handshake"


def test_not_connected_answer_fails_the_request_and_drops_the_link():
    core = LinkCore()
    core.step(0.0)
    reply_handshake(core, 0.01)
    req = core.command(pb.CMD_NOOP, now_s=0.1)
    p = Packet(seq=2, ack_seq=req.seq)
    p.ack.accepted = False
    p.ack.reason = pb.NACK_NOT_CONNECTED
    core.receive(encode_frame(p), 0.12)
    assert req.done and not req.accepted and req.response.reason == pb.NACK_NOT_CONNECTED
    assert not core.link_up


def test_caller_heartbeats_go_out_only_when_called_and_gate_the_re_handshake():
    core = LinkCore(auto_heartbeat=False)
    core.heartbeat(0.0)  # the caller's loop is alive
    core.step(0.0)
    reply_handshake(core, 0.01)
    for t in (0.3, 0.6, 0.9):
        core.step(t)
    assert not [p for p in sent(core) if p.WhichOneof("body") == "heartbeat"], "none unless called"
    assert core.heartbeat(1.0)
    assert not core.heartbeat(1.05), "at most one per heartbeat period"
    core.receive(telemetry(2, 2000), 1.5)
    core.step(1.5)
    assert core.link_up
    core.receive(telemetry(3, 2600, host_link_alive=False), 2.1)  # the MCU timed the hung host out
    assert not core.link_up
    sent(core)
    for t in (2.2, 2.5, 3.0):  # the caller is still hung: no handshake behind its back
        core.step(t)
    assert not core.busy and not sent(core)
    core.heartbeat(3.1)  # the loop cycles again
    core.step(3.1)
    assert core.busy and core.pending.kind == "handshake"
