"""LinkClient against the fake MCU: handshake, requests, retransmission, link loss,
reconnection, thread safety, shutdown; and the ``oibar link`` CLI on top of it."""

from __future__ import annotations

import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
from fake_mcu import FakeMcu, PtyBridge, wait_for

from oibar import cli, pb
from oibar.link import (
    LinkClient,
    LinkClosed,
    LinkDown,
    LinkError,
    LinkTimeout,
    Nack,
    PortError,
    ProtocolVersionError,
)
from oibar.link.core import LinkCore
from oibar.link.seq import SEQ_MAX


def connected(make_client, mcu, **overrides) -> LinkClient:
    client = make_client(mcu.url, **overrides)
    client.connect()
    return client


# -- handshake ----------------------------------------------------------------------------------


def test_handshake_reports_the_mcu_info(mcu, make_client):
    client = make_client(mcu.url, host_version="test-host-9")
    info = client.connect()
    assert info.firmware_version == "fake-1.2.3"
    assert info.build_id == "fake-build-0001"
    assert info.protocol_version == pb.PROTOCOL_VERSION == 2
    assert info.reset_cause == "RESET_POWER_ON"
    assert 0 <= info.uptime_ms < 60_000
    assert client.link_alive and client.handshake_info == info
    (handshake,) = mcu.requests("handshake")
    assert handshake.seq == 1  # a new session starts numbering at 1
    assert handshake.handshake.protocol_version == pb.PROTOCOL_VERSION
    assert handshake.handshake.host_version == "test-host-9"
    assert mcu.connected


def test_mcu_with_another_protocol_version_is_refused(mcu, make_client):
    mcu.protocol_version = 7
    client = make_client(mcu.url)
    with pytest.raises(ProtocolVersionError) as caught:
        client.connect()
    assert (caught.value.host_version, caught.value.mcu_version) == (2, 7)
    assert "version 2" in str(caught.value) and "version 7" in str(caught.value)
    assert not client.link_alive
    with pytest.raises(LinkDown):
        client.command("NOOP")
    # connect() may be retried once the firmware is right
    mcu.protocol_version = pb.PROTOCOL_VERSION
    assert client.connect().protocol_version == 2


def test_host_with_another_protocol_version_is_refused_by_the_mcu(mcu, make_client):
    client = make_client(mcu.url, protocol_version=3)
    with pytest.raises(ProtocolVersionError, match="version 3.*version 2"):
        client.connect()
    assert not mcu.connected


def test_unopenable_port_raises_port_error(make_client):
    with pytest.raises(PortError, match="cannot open"):
        make_client("socket://127.0.0.1:1").connect()
    with pytest.raises(PortError):
        make_client("/dev/oibar-no-such-port").connect()


def test_connect_times_out_when_nobody_answers(make_client):
    # loop:// echoes our own frames: they decode fine but are requests, not responses.
    client = make_client("loop://")
    started = time.monotonic()
    with pytest.raises(LinkTimeout, match="4 attempts"):
        client.connect()
    assert time.monotonic() - started < 1.0
    stats = client.statistics
    assert stats.timeouts == 1 and stats.retransmissions == 3
    assert stats.rx_packets >= 4  # our four handshakes, echoed and ignored


@pytest.mark.skipif(not hasattr(os, "openpty"), reason="needs a POSIX pseudo-terminal")
def test_client_over_a_real_serial_device(mcu, make_client):
    """pyserial's posix Serial (termios, TIOCINQ), as with a USB CDC port or the C peer."""
    bridge = PtyBridge(mcu)
    try:
        client = make_client(bridge.device)
        assert client.connect().firmware_version == "fake-1.2.3"
        assert client.command("NOOP").accepted
        assert client.param_get(3).name == "latch_speed_sps"
        assert wait_for(lambda: client.telemetry is not None)
        client.close()
    finally:
        bridge.close()


def test_missing_generated_module_says_to_run_make_gen():
    host_dir = Path(__import__("oibar").__file__).resolve().parents[1]
    code = "import sys; sys.modules['oibar._generated.oibar_pb2'] = None\nimport oibar.pb"
    proc = subprocess.run(
        [sys.executable, "-c", code],
        capture_output=True,
        text=True,
        env={**os.environ, "PYTHONPATH": str(host_dir)},
        timeout=30,
    )
    assert proc.returncode != 0
    assert "ImportError" in proc.stderr and "run `make gen` at the repository root" in proc.stderr


# -- requests -----------------------------------------------------------------------------------


def test_command_accepted_and_refused(mcu, make_client):
    client = connected(make_client, mcu)
    noop = client.command("NOOP")
    assert (noop.accepted, noop.reason, noop.state) == (True, "NACK_NONE", "STATE_IDLE")
    armed = client.command("CMD_APPROACH_ARM")
    assert (armed.accepted, armed.state) == (True, "STATE_APPROACH_READY")
    again = client.command(pb.CMD_APPROACH_ARM)
    assert (again.accepted, again.reason, again.state) == (
        False,
        "NACK_INVALID_IN_STATE",
        "STATE_APPROACH_READY",
    )
    with pytest.raises(Nack) as caught:
        client.command_checked("approach_arm")
    assert caught.value.reason == "NACK_INVALID_IN_STATE"
    assert "CMD_APPROACH_ARM" in str(caught.value)
    assert client.command_checked("ABORT").state == "STATE_IDLE"
    assert mcu.executed == [pb.CMD_NOOP, pb.CMD_APPROACH_ARM, pb.CMD_ABORT]


def test_command_names_are_validated_before_sending(mcu, make_client):
    client = connected(make_client, mcu)
    with pytest.raises(ValueError, match="unknown command 'FLY'.*NOOP"):
        client.command("FLY")
    assert mcu.requests("command") == []


def test_nack_reason_from_the_mcu_is_reported(mcu, make_client):
    client = connected(make_client, mcu)
    mcu.opcode_nacks[pb.CMD_DOCK] = pb.NACK_PRECONDITION_FAILED
    result = client.command("DOCK")
    assert not result.accepted and result.reason == "NACK_PRECONDITION_FAILED"


def test_start_transfer_carries_the_target_pressure(mcu, make_client):
    client = connected(make_client, mcu)
    assert client.command("START_TRANSFER", target_pressure_kpa=1200.5).accepted
    assert mcu.requests("command")[-1].command.target_pressure_kpa == pytest.approx(1200.5)
    assert client.command("START_TRANSFER").reason == "NACK_BAD_ARGUMENT"


def test_param_get_and_set(mcu, make_client):
    client = connected(make_client, mcu)
    value = client.param_get(1)
    assert value.ok and value.param_id == 1 and value.name == "transfer_target_kpa"
    assert (value.value, value.min, value.max, value.unit) == (200.0, 0.0, 500.0, "kPa")
    updated = client.param_set(1, 321.5)
    assert updated.ok and updated.value == pytest.approx(321.5)
    refused = client.param_set(1, 9999.0)
    assert refused.reason == "NACK_PARAM_OUT_OF_BOUNDS" and refused.value == pytest.approx(321.5)
    unknown = client.param_get(99)
    assert not unknown.ok and unknown.reason == "NACK_UNKNOWN_PARAM"
    with pytest.raises(Nack, match="NACK_UNKNOWN_PARAM"):
        unknown.raise_for_nack()


def test_retransmission_reuses_the_seq_and_the_mcu_executes_once(mcu, make_client):
    client = connected(make_client, mcu)
    mcu.drop_responses(2)
    result = client.command("APPROACH_ARM")
    # Executed once: a second execution would have answered NACK_INVALID_IN_STATE.
    assert (result.accepted, result.state) == (True, "STATE_APPROACH_READY")
    sent = mcu.requests("command")
    assert len(sent) == 3
    assert len({p.seq for p in sent}) == 1
    assert mcu.executed == [pb.CMD_APPROACH_ARM]
    assert mcu.rx_duplicates == 2 and mcu.dropped_responses == 2
    stats = client.statistics
    assert (stats.retransmissions, stats.timeouts) == (2, 0)
    # the next request gets a fresh seq, and the retransmissions were not seen as losses
    client.command("NOOP")
    assert mcu.requests("command")[-1].seq > sent[0].seq
    assert mcu.lost_host_packets == 0


def test_timeout_when_the_mcu_never_answers(mcu, make_client):
    client = connected(make_client, mcu)
    mcu.drop_responses(1_000_000)
    started = time.monotonic()
    with pytest.raises(LinkTimeout, match="4 attempts"):
        client.command("NOOP")
    elapsed = time.monotonic() - started
    assert 0.19 <= elapsed < 0.6  # (1 + max_retries) * retransmit_timeout_s = 0.2 s
    sent = mcu.requests("command")
    assert len(sent) == 4 and len({p.seq for p in sent}) == 1
    assert client.statistics.timeouts == 1 and client.statistics.retransmissions == 3
    assert mcu.executed == [pb.CMD_NOOP]
    # telemetry kept flowing: the link is still up and usable once answers come back
    assert client.link_alive
    mcu.drop_responses(0)
    assert client.command("NOOP").accepted


def test_unmatched_late_responses_are_ignored(mcu, make_client):
    client = connected(make_client, mcu)
    mcu.response_delay_s = 0.12  # answers arrive after two retransmissions
    assert client.command("NOOP").accepted
    mcu.response_delay_s = 0.0
    assert client.command("ABORT").accepted  # a late duplicate must not answer this one
    assert wait_for(lambda: client.statistics.unmatched_responses >= 1)
    assert mcu.executed == [pb.CMD_NOOP, pb.CMD_ABORT]


def test_concurrent_requests_get_their_own_responses(mcu, make_client):
    client = connected(make_client, mcu, retransmit_timeout_s=0.5)
    mcu.response_delay_s = 0.001
    errors: list[str] = []

    def worker(index: int) -> None:
        try:
            for round_ in range(10):
                param_id = 1 + (index + round_) % 12
                value = client.param_get(param_id)
                if value.param_id != param_id or not value.ok:
                    errors.append(f"thread {index}: asked {param_id}, got {value}")
                if round_ % 3 == 0:
                    result = client.command("NOOP")
                    if not result.accepted:
                        errors.append(f"thread {index}: NOOP refused {result}")
        except Exception as exc:  # pragma: no cover - reported below
            errors.append(f"thread {index}: {exc!r}")

    threads = [threading.Thread(target=worker, args=(i,)) for i in range(8)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(10)
    assert errors == []
    assert len(mcu.requests("param_get")) == 80
    assert mcu.executed.count(pb.CMD_NOOP) == 8 * 4
    assert client.statistics.retransmissions == 0


# -- telemetry, events, nav ---------------------------------------------------------------------


def test_telemetry_latest_rate_and_callback(mcu, make_client):
    received = []
    client = make_client(mcu.url, on_telemetry=received.append)
    client.connect()
    assert wait_for(lambda: len(received) >= 8)
    assert client.telemetry is not None and client.telemetry.state == pb.STATE_IDLE
    assert client.telemetry.host_link_alive
    assert 8 < client.telemetry_rate_hz < 40  # the fake sends every 50 ms


def test_events_are_queued_and_called_back(mcu, make_client):
    seen = []
    client = make_client(mcu.url, on_event=seen.append)
    client.connect()
    first = client.next_event(timeout_s=1.0)
    assert first is not None and first.id == pb.EVT_LINK_UP
    client.command("APPROACH_ARM")
    change = client.next_event(timeout_s=1.0)
    assert change.id == pb.EVT_STATE_CHANGE
    assert (change.from_state, change.to_state) == (pb.STATE_IDLE, pb.STATE_APPROACH_READY)
    assert [e.id for e in seen] == [pb.EVT_LINK_UP, pb.EVT_STATE_CHANGE]
    assert client.next_event(timeout_s=0.01) is None


def test_event_queue_is_bounded(mcu, make_client):
    client = connected(make_client, mcu, event_queue_size=3)
    for arg in range(6):
        mcu.emit_event(pb.EVT_PARAM_CHANGED, arg=arg)
    assert wait_for(lambda: client.statistics.events_dropped >= 4)
    assert [client.next_event(0.1).arg for _ in range(3)] == [3, 4, 5]  # the newest are kept


def test_send_nav_is_fire_and_forget(mcu, make_client):
    client = connected(make_client, mcu)
    assert client.send_nav(
        frame_id=42,
        t_cam_target_m=(-0.1, 0.02, 4.25),
        q_cam_target=(1.0, 0.0, 0.0, 0.0),
        range_m=4.25,
        closing_speed_mps=0.05,
        phase="NAV_PHASE_FORCED_TRANSLATION",
        confidence=0.9,
    )
    assert mcu.wait_until(lambda m: len(m.nav_updates) == 1)
    nav = mcu.nav_updates[0]
    assert nav.frame_id == 42 and nav.phase == pb.NAV_PHASE_FORCED_TRANSLATION
    assert nav.t_cam_target_m.z == pytest.approx(4.25) and nav.q_cam_target.w == 1.0
    assert mcu.requests("nav_update")[0].seq != 0


def test_heartbeats_are_sent_and_numbered(mcu, make_client):
    client = connected(make_client, mcu)
    assert mcu.wait_until(lambda m: len(m.requests("heartbeat")) >= 4)
    seqs = [p.seq for p in mcu.received]
    assert seqs == sorted(seqs) and len(set(seqs)) == len(seqs)
    assert mcu.lost_host_packets == 0
    assert client.statistics.tx_packets >= 5


def test_gaps_in_the_mcu_seq_are_counted_as_lost(mcu, make_client):
    client = connected(make_client, mcu)
    assert wait_for(lambda: client.statistics.rx_packets >= 3)
    mcu.skip_seq(5)
    assert wait_for(lambda: client.statistics.lost_peer_packets == 5)
    time.sleep(0.1)
    assert client.statistics.lost_peer_packets == 5


def test_bad_frames_from_the_mcu_are_counted(mcu, make_client):
    client = connected(make_client, mcu)
    mcu.send_raw(b"\x00\x13\x37\x00" + b"\x55" * 300 + b"\x00")
    assert wait_for(lambda: client.statistics.rx_framing_errors == 1)
    assert wait_for(lambda: client.statistics.rx_oversize == 1)
    assert client.link_alive and client.command("NOOP").accepted


def test_requests_from_a_callback_are_refused(mcu, make_client):
    outcome = []

    def on_telemetry(_telemetry):
        if not outcome:
            try:
                client.command("NOOP")
                outcome.append("sent")
            except LinkError as exc:
                outcome.append(str(exc))

    client = make_client(mcu.url, on_telemetry=on_telemetry)
    client.connect()
    assert wait_for(lambda: outcome)
    assert "callback" in outcome[0]


def test_peer_seq_tracking_handles_wrap_stale_and_restart():
    core = LinkCore()  # the one place the rule is applied, for LinkClient and LinkSession alike
    track = core._track_peer_seq
    for seq in (SEQ_MAX - 1, SEQ_MAX, 1, 2):  # wrap: SEQ_MAX is followed by 1
        track(seq)
    assert core.counters.lost_peer_packets == 0
    track(5)  # 3 and 4 lost
    assert core.counters.lost_peer_packets == 2
    track(4)  # an old packet sent again (cached response): neither counted nor tracked
    track(6)
    assert core.counters.lost_peer_packets == 2
    track(0)  # seq 0 means none
    for _ in range(2):  # twice, a gap across the wrap each time: SEQ_MAX and 1 lost
        core._peer_seq = None
        track(SEQ_MAX - 1)
        track(2)
    assert core.counters.lost_peer_packets == 2 + 2 * 2
    core._peer_seq = 50_000
    track(1)  # far behind: the peer restarted its numbering
    track(2)
    assert core.counters.lost_peer_packets == 6 and core._peer_seq == 2


# -- link loss and recovery ---------------------------------------------------------------------


def test_link_loss_when_the_peer_goes_silent_and_recovery(mcu, make_client):
    states: list[bool] = []
    client = make_client(mcu.url, on_link_state=states.append)
    client.connect()
    assert states == [True]
    mcu.go_silent()
    silent_at = time.monotonic()
    assert wait_for(lambda: not client.link_alive, timeout_s=2.0)
    detected_after = time.monotonic() - silent_at
    assert 0.25 <= detected_after < 0.6  # link_timeout_s = 0.3
    assert wait_for(lambda: states == [True, False])
    started = time.monotonic()
    with pytest.raises(LinkDown):
        client.command("NOOP")
    assert time.monotonic() - started < 0.05  # fails fast, no retransmissions
    assert not client.send_nav(frame_id=1)
    mcu.resume()
    assert wait_for(lambda: client.link_alive, timeout_s=3.0)
    assert wait_for(lambda: states == [True, False, True])
    assert client.statistics.reconnects == 1
    assert client.command("NOOP").accepted
    # the re-handshake opened a new numbering session
    assert mcu.requests("handshake")[-1].seq == 1


def test_link_loss_fails_a_waiting_request_with_link_down(mcu, make_client):
    client = connected(make_client, mcu, retransmit_timeout_s=1.0, max_retries=2)
    mcu.go_silent()
    started = time.monotonic()
    with pytest.raises(LinkDown, match="link lost"):
        client.command("NOOP")
    assert time.monotonic() - started < 0.8  # link_timeout_s, not the 3 s of retries


def test_reconnect_after_the_port_disappears_and_comes_back(mcu, make_client):
    states: list[bool] = []
    client = make_client(mcu.url, on_link_state=states.append)
    client.connect()
    mcu.disappear()
    assert wait_for(lambda: not client.link_alive, timeout_s=2.0)
    with pytest.raises(LinkDown):
        client.command("NOOP")
    time.sleep(0.35)  # a few failed re-open attempts (reconnect_period_s = 0.1)
    assert not client.link_alive
    mcu.reappear()
    assert wait_for(lambda: client.link_alive, timeout_s=5.0)
    assert client.command("NOOP").accepted
    assert states == [True, False, True]
    assert client.statistics.reconnects == 1
    assert mcu.connections == 2 and mcu.handshakes_accepted == 2


def test_not_connected_answer_triggers_a_new_handshake(mcu, make_client):
    states: list[bool] = []
    client = make_client(mcu.url, on_link_state=states.append)
    client.connect()
    # As after a quick MCU reset the host did not notice. Telemetry muted until the new
    # handshake: its host_link_alive = false would tell the client too (another path, with its
    # own test), and that race is not this test's.
    mcu.mute_telemetry(True)
    mcu.forget_host()
    result = client.command("NOOP")
    assert (result.accepted, result.reason) == (False, "NACK_NOT_CONNECTED")
    assert wait_for(lambda: client.link_alive and mcu.handshakes_accepted == 2, timeout_s=3.0)
    mcu.mute_telemetry(False)
    assert client.command("NOOP").accepted
    assert wait_for(lambda: states == [True, False, True])


def test_mcu_reboot_is_noticed_without_a_request_and_the_link_comes_back(mcu, make_client):
    """Issue 17: the MCU restarts (watchdog) behind a port that stays open. Its uptime goes back
    and its telemetry says the host link is down; the client must see that by itself (not wait
    for a refused command) and handshake again."""
    states: list[bool] = []
    client = make_client(mcu.url, on_link_state=states.append)
    client.connect()
    assert wait_for(lambda: client.statistics.rx_packets >= 3)
    mcu.reboot()
    assert wait_for(lambda: states == [True, False, True], timeout_s=3.0), states
    # one loss and one new session; a late reply on a loaded machine may have the client send its
    # handshake again (same seq, which the MCU always handles: each counts as accepted)
    stats = client.statistics
    assert client.link_alive and stats.link_losses == 1
    assert 2 <= mcu.handshakes_accepted <= 2 + stats.retransmissions
    assert stats.mcu_restarts >= 1
    assert client.command("NOOP").accepted


# -- shutdown -----------------------------------------------------------------------------------


def test_close_while_a_request_is_blocked(mcu, make_client):
    client = connected(make_client, mcu, retransmit_timeout_s=2.0, max_retries=5)
    mcu.drop_responses(1_000_000)
    outcome: list[BaseException] = []

    def call():
        try:
            client.command("NOOP")
        except BaseException as exc:
            outcome.append(exc)

    caller = threading.Thread(target=call)
    caller.start()
    # >= 1: on a loaded machine a retransmission may already have gone out.
    assert mcu.wait_until(lambda m: len(m.requests("command")) >= 1)
    started = time.monotonic()
    client.close()
    caller.join(6.0)
    assert not caller.is_alive()
    # Retransmitting to the end would take 2 s x 6 attempts; close() must cut that short
    # (generous bound: a loaded 2-core CI machine is slow to schedule threads).
    assert time.monotonic() - started < 5.0
    assert len(outcome) == 1 and isinstance(outcome[0], LinkClosed)


def test_close_is_idempotent_and_final(mcu, make_client):
    with make_client(mcu.url) as client:
        client.connect()
    client.close()
    client.close()
    assert not client.link_alive
    with pytest.raises(LinkClosed):
        client.command("NOOP")
    with pytest.raises(LinkClosed):
        client.connect()
    while client.next_event(timeout_s=0) is not None:  # queued events stay readable
        pass
    assert client.next_event(timeout_s=None) is None  # but a closed client never blocks


def test_close_without_connect_and_from_a_callback(mcu, make_client):
    make_client(mcu.url).close()
    done = threading.Event()

    def close_from_callback(_telemetry):
        client.close()
        done.set()

    client = make_client(mcu.url, on_telemetry=close_from_callback)
    client.connect()
    assert done.wait(2.0)
    assert wait_for(
        lambda: not any(t.is_alive() for t in threading.enumerate() if t.name.startswith("oibar-link-"))
    )


def test_connect_twice_is_an_error(mcu, make_client):
    client = connected(make_client, mcu)
    with pytest.raises(LinkError, match="already connected"):
        client.connect()


# -- CLI ----------------------------------------------------------------------------------------


def test_cli_link_connects_sends_commands_and_shows_status(mcu, capsys):
    code = cli.main(
        [
            "link",
            "--port",
            mcu.url,
            "--seconds",
            "1.1",
            "--command",
            "NOOP",
            "cmd_approach_arm",
            "APPROACH_ARM",
        ]
    )
    out, err = capsys.readouterr()
    assert code == 0, err
    lines = out.splitlines()
    assert "firmware fake-1.2.3" in lines[0] and "protocol 2" in lines[0]
    assert lines[1] == "CMD_NOOP: accepted, reason NACK_NONE, state STATE_IDLE"
    assert lines[2] == "CMD_APPROACH_ARM: accepted, reason NACK_NONE, state STATE_APPROACH_READY"
    assert lines[3].startswith("CMD_APPROACH_ARM: REFUSED, reason NACK_INVALID_IN_STATE")
    status = [line for line in lines[4:] if "link UP" in line]
    assert status and "STATE_APPROACH_READY" in status[-1] and "Hz" in status[-1]


def test_cli_port_error_is_one_line_and_exit_2(capsys):
    code = cli.main(["link", "--port", "socket://127.0.0.1:1", "--seconds", "0"])
    out, err = capsys.readouterr()
    assert code == 2
    assert err.startswith("oibar: error: cannot open socket://127.0.0.1:1")
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1


def test_cli_version_mismatch_is_exit_2(capsys):
    with FakeMcu(protocol_version=9) as mcu:
        code = cli.main(["link", "--port", mcu.url, "--seconds", "0"])
    _, err = capsys.readouterr()
    assert code == 2 and "version 2" in err and "version 9" in err


def test_cli_timeout_is_exit_2(capsys):
    code = cli.main(["link", "--port", "loop://", "--seconds", "0"])
    _, err = capsys.readouterr()
    assert code == 2 and "no answer from the MCU" in err


def test_cli_unknown_command_name_is_a_usage_error(capsys):
    with pytest.raises(SystemExit) as caught:
        cli.main(["link", "--port", "loop://", "--command", "FLY"])
    assert caught.value.code == 2
    assert "unknown command 'FLY'" in capsys.readouterr().err


def test_cli_help_explains_the_link_subcommand(capsys):
    with pytest.raises(SystemExit) as caught:
        cli.main(["link", "--help"])
    assert caught.value.code == 0
    text = capsys.readouterr().out
    for needle in ("--port", "socket://", "--seconds", "--command", "APPROACH_ARM", "exit status"):
        assert needle in text
    assert cli.main([]) == 2


def test_a_host_version_the_mcu_cannot_decode_is_refused_up_front():
    # The MCU's nanopb struct holds 16 bytes; a longer string would make it drop the handshake.
    with pytest.raises(ValueError, match="16 bytes"):
        LinkClient("loop://", host_version="x" * 17)
    LinkClient("loop://", host_version="x" * 16).close()
