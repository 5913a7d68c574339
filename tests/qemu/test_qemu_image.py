"""The flashable STM32F405 image itself, booted on QEMU's ``netduinoplus2`` board.

QEMU runs ``build/fw-arm-qemu/oibar_stm32f4.elf`` (the emulator image, built by ``make
firmware-arm-qemu`` with OIBAR_QEMU=ON: the flight image has no emulator workaround) with USART1 bound
to a loopback TCP socket; the host's own :class:`oibar.link.LinkClient` talks to it over
``socket://127.0.0.1:PORT`` exactly as it would talk to a board on a serial port.

What the emulated board looks like to the firmware (QEMU 7.2, see docs/hardware.md):

- USART1, SysTick, TIM2-5 and the NVIC are modelled, so the link, the time base and the
  step timer run for real;
- RCC, GPIO, IWDG and PWR are stubs that read 0: RCC_CSR carries no reset flag (reset cause
  RESET_UNKNOWN), every switch input reads "not actuated" (the connector sense loop, wired
  active low, reads "mated"), and the clock set-up finds no RCC to program;
- the ADC never completes a conversion (EOC never rises), so the port reports every channel
  as stale and the application, correctly, latches FAULT_PRESSURE_SENSOR_RANGE a few
  milliseconds after boot and stays in STATE_FAULT. From STATE_FAULT the state table
  (docs/state_table.md) allows no transition while the pressure sensors are unhealthy, so
  these tests check the honest behaviour: refused commands carry their reason, the valid
  command is accepted without a transition, and a host-link loss is counted and survived.
"""

from __future__ import annotations

import contextlib
import shutil
import socket
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from oibar import pb
from oibar.link import LinkClient
from oibar.link.errors import LinkError

ROOT = Path(__file__).resolve().parents[2]
FW_ARM = ROOT / "build" / "fw-arm-qemu"
IMAGE = FW_ARM / "oibar_stm32f4.elf"

# QEMU's clock is the host's, but a loaded CI machine can stall it: generous bounds.
BOOT_TIMEOUT_S = 20.0
TELEMETRY_TIMEOUT_S = 10.0
LINK_TIMEOUT_MS = 1000  # the firmware's default link_timeout (docs/link.md)


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class QemuBoard:
    """One qemu-system-arm process running the image, its USART1 on a TCP port."""

    def __init__(self, log_path: Path) -> None:
        self.log_path = log_path
        self.proc: subprocess.Popen[bytes] | None = None
        self.port = 0

    @property
    def url(self) -> str:
        return f"socket://127.0.0.1:{self.port}"

    def start(self) -> None:
        qemu = shutil.which("qemu-system-arm")
        if qemu is None:
            pytest.fail("qemu-system-arm is not installed: run `make setup` (Debian package qemu-system-arm)")
        # The port is free when picked but could be taken before QEMU binds it: retry.
        for _attempt in range(3):
            self.port = _free_port()
            cmd = [
                qemu,
                "-M",
                "netduinoplus2",
                "-nographic",
                "-monitor",
                "none",
                # A reset of the firmware (fatal-error handler) ends QEMU, so the test sees it.
                "-no-reboot",
                "-kernel",
                str(IMAGE),
                # nodelay: without it Nagle holds the UART's byte-by-byte output for a delayed
                # ACK (~40 ms a round trip), which on a loaded CI runner made handshakes retry.
                "-chardev",
                f"socket,id=link,host=127.0.0.1,port={self.port},server=on,wait=off,nodelay=on",
                "-serial",
                "chardev:link",
            ]
            with open(self.log_path, "wb") as log:
                self.proc = subprocess.Popen(
                    cmd, stdin=subprocess.DEVNULL, stdout=log, stderr=subprocess.STDOUT
                )
            if self._wait_listening():
                return
            self.stop()
        pytest.fail(f"QEMU did not start; its output:\n{self.log_tail()}")

    def _wait_listening(self) -> bool:
        deadline = time.monotonic() + BOOT_TIMEOUT_S
        while time.monotonic() < deadline:
            assert self.proc is not None
            if self.proc.poll() is not None:
                return False
            # QEMU listens with wait=off: a probe connection shows the port is up. It is
            # closed at once; the chardev then waits for the next client.
            with (
                contextlib.suppress(OSError),
                socket.create_connection(("127.0.0.1", self.port), timeout=0.5),
            ):
                return True
            time.sleep(0.1)
        return False

    def alive(self) -> bool:
        return self.proc is not None and self.proc.poll() is None

    def stop(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(timeout=10)

    def log_tail(self) -> str:
        try:
            return self.log_path.read_text(errors="replace")[-3000:]
        except OSError:
            return "(no QEMU output)"


@pytest.fixture(scope="module")
def board(tmp_path_factory: pytest.TempPathFactory) -> Iterator[QemuBoard]:
    if not IMAGE.is_file():
        pytest.fail(f"{IMAGE.relative_to(ROOT)} is missing: run `make firmware-arm` first")
    qemu = QemuBoard(tmp_path_factory.mktemp("qemu") / "qemu.log")
    qemu.start()
    try:
        yield qemu
    finally:
        qemu.stop()


@contextlib.contextmanager
def connected(board: QemuBoard) -> Iterator[LinkClient]:
    """A LinkClient that has completed its handshake with the emulated board."""
    deadline = time.monotonic() + BOOT_TIMEOUT_S
    last: Exception | None = None
    while time.monotonic() < deadline:
        assert board.alive(), f"QEMU exited; its output:\n{board.log_tail()}"
        client = LinkClient(board.url, retransmit_timeout_s=0.5, max_retries=4)
        try:
            client.connect()
        except LinkError as exc:  # QEMU still booting, or the previous client's socket lingering
            last = exc
            client.close()
            time.sleep(0.3)
            continue
        try:
            yield client
        finally:
            client.close()
        return
    pytest.fail(f"no handshake with the emulated board within {BOOT_TIMEOUT_S} s: {last}")


def wait_telemetry(link: LinkClient, newer_than_ms: int = -1, *, host_link_alive: bool = False):
    """The first telemetry with uptime_ms above `newer_than_ms` (and, if asked, one that
    reports the host link alive: a frame sent just before the MCU processed our handshake
    can still be in flight, so the first new frame may predate the reconnection)."""
    deadline = time.monotonic() + TELEMETRY_TIMEOUT_S
    last = None
    while time.monotonic() < deadline:
        t = link.telemetry
        if t is not None and t.uptime_ms > newer_than_ms:
            last = t
            if t.host_link_alive or not host_link_alive:
                return t
        time.sleep(0.02)
    want = " reporting the host link alive" if host_link_alive else ""
    pytest.fail(
        f"no telemetry newer than {newer_than_ms} ms{want} within {TELEMETRY_TIMEOUT_S} s; last seen:\n{last}"
    )


def fault_bit(name: str) -> int:
    return 1 << (pb.FaultCode.Value(name) - 1)


def state_name(value: int) -> str:
    return pb.State.Name(value)


def test_handshake_reports_build_id_version_and_reset_cause(board: QemuBoard) -> None:
    expected_build_id = (FW_ARM / "build_id.txt").read_text().strip()
    expected_version = (FW_ARM / "firmware_version.txt").read_text().strip()
    with connected(board) as link:
        info = link.handshake_info
        assert info is not None
        assert info.build_id == expected_build_id
        assert info.build_id  # never empty: the build injects git describe or "unknown"
        assert info.firmware_version == expected_version
        assert info.protocol_version == pb.PROTOCOL_VERSION
        # QEMU's RCC is a stub: RCC_CSR reads 0, no reset flag, so the port says UNKNOWN
        # (on a board a power-up reads RESET_POWER_ON).
        assert info.reset_cause == "RESET_UNKNOWN"
        assert info.uptime_ms > 0


def test_telemetry_streams_with_the_state_the_emulated_sensors_cause(board: QemuBoard) -> None:
    with connected(board) as link:
        # host_link_alive: sent after the MCU took our handshake, so its counters already hold
        # whatever the switch from the previous test's client cost (see below).
        first = wait_telemetry(link, host_link_alive=True)
        time.sleep(1.5)
        later = wait_telemetry(link, first.uptime_ms)
        # 10 Hz nominal; QEMU on a busy machine may lag, so only a floor.
        assert link.telemetry_rate_hz > 4.0
        # The firmware clock runs at about real time (SysTick at the nominal 168 MHz).
        assert 500 <= later.uptime_ms - first.uptime_ms <= 5000
        assert later.host_link_alive
        # The MCU's counters are cumulative over the module's one board. A client that connects
        # within milliseconds of the previous test's close() can lose its first handshake frame
        # in QEMU's chardev socket hand-over (one framing error, then the retransmission is
        # answered); what this session streams must be clean.
        assert later.link.rx_crc_errors == first.link.rx_crc_errors
        assert later.link.rx_framing_errors == first.link.rx_framing_errors
        # The ADC never converts under QEMU: stale transducers -> sensor fault -> FAULT.
        assert state_name(later.state) == "STATE_FAULT"
        assert later.fault_flags & fault_bit("FAULT_PRESSURE_SENSOR_RANGE")
        # Safe outputs whatever the state: valves commanded closed.
        assert not later.sv_valve_cmd_open and not later.tv_valve_cmd_open
        # GPIO reads 0: switches not actuated, connector sense (active low) reads mated.
        assert not later.contact and not later.latch_engaged
        # Both latch contacts (active low) read closed: an implausible pair, a sensor fault.
        assert later.fault_flags & fault_bit("FAULT_LATCH_SENSOR")
        assert later.connector_mated


def test_invalid_commands_are_refused_with_their_reason(board: QemuBoard) -> None:
    with connected(board) as link:
        # No CMD_DOCK row for STATE_FAULT: refused because a fault is latched.
        r = link.command("DOCK")
        assert (r.accepted, r.reason, r.state) == (False, "NACK_FAULT_ACTIVE", "STATE_FAULT")
        # CMD_CLEAR_FAULT exists but its guard (sensors healthy) fails.
        r = link.command("CLEAR_FAULT")
        assert (r.accepted, r.reason, r.state) == (False, "NACK_PRECONDITION_FAILED", "STATE_FAULT")
        # An opcode the firmware does not know.
        r = link.command(999)
        assert (r.accepted, r.reason) == (False, "NACK_UNKNOWN_OPCODE")
        assert state_name(wait_telemetry(link).state) == "STATE_FAULT"


def test_valid_command_is_accepted(board: QemuBoard) -> None:
    with connected(board) as link:
        # STATE_FAULT | CMD_ABORT | - | - : accepted, stays in FAULT (valves already closed).
        r = link.command("ABORT")
        assert (r.accepted, r.reason, r.state) == (True, "NACK_NONE", "STATE_FAULT")
        r = link.command("NOOP")
        assert (r.accepted, r.reason, r.state) == (True, "NACK_NONE", "STATE_FAULT")


def test_heartbeat_loss_is_detected_and_survived(board: QemuBoard) -> None:
    with connected(board) as link:
        before = wait_telemetry(link)
        # The client's close() stops its heartbeats: the host goes silent.
    silent_from = time.monotonic()
    time.sleep(2.5 * LINK_TIMEOUT_MS / 1000.0)
    assert board.alive(), f"QEMU exited; its output:\n{board.log_tail()}"
    with connected(board) as link:
        assert time.monotonic() - silent_from > LINK_TIMEOUT_MS / 1000.0
        # The MCU must come back to reporting the host link alive within the timeout.
        after = wait_telemetry(link, before.uptime_ms, host_link_alive=True)
        # The MCU counted the loss, dropped to unconnected (this handshake was accepted
        # anew) and is back up; no reboot in between (uptime went on).
        assert after.link.link_losses >= before.link.link_losses + 1
        assert after.uptime_ms > before.uptime_ms
        # Reaction of the application: in STATE_FAULT a link loss changes nothing
        # (state table: STATE_FAULT | SIG_LINK_DOWN | - | -); valves stay closed.
        assert state_name(after.state) == "STATE_FAULT"
        assert not after.sv_valve_cmd_open and not after.tv_valve_cmd_open
        assert after.fault_flags & fault_bit("FAULT_PRESSURE_SENSOR_RANGE")
