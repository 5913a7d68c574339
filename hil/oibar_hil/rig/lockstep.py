"""The plant's end of the lockstep channel to the simulated MCU (docs/hil.md).

Mirrors ``firmware/port/sim/include/oibar/sim_lockstep.h``: one exchange sends the sensor
inputs and how many milliseconds to run, and returns the actuator outputs of that interval.
Frames are numbered; the MCU refuses a lost or repeated frame and the plant checks the
echo and the cumulative step-pulse count, so neither side can silently drift.
"""

from __future__ import annotations

import os
import select
import socket
import struct
import subprocess
import tty
from dataclasses import dataclass
from pathlib import Path

PLANT_MAGIC = 0x5053424F  # "OBSP"
MCU_MAGIC = 0x4D53424F  # "OBSM"
VERSION = 1
ADC_SLOTS = 8
MAX_ADVANCE_MS = 100
FLAG_HANG_MAIN_LOOP = 0x1
FLAG_QUIT = 0x2
FLAG_RESET_PIN = 0x4  # the MCU restarts before the exchange runs (sim_lockstep.h)
MCU_STEP_TIMER_RUNNING = 0x1
MCU_MAIN_HUNG = 0x2
STATUS_NAMES = {0: "OK", 1: "ERR_FRAME", 2: "ERR_MAGIC", 3: "ERR_ADVANCE", 4: "ERR_SIZE"}

_PLANT = struct.Struct("<8I8H")
_MCU = struct.Struct("<21I")
_MCU_FIELDS = (
    "magic version frame status expected_frame sim_time_ms uptime_ms do_bits do_any_bits "
    "steps_fwd steps_rev steps_total uart_tx_bytes uart_rx_pending resets reset_cause "
    "watchdog_kicks flags app_state valve_violation_ms fault_flags"
).split()

# hal.h enums, by meaning (the bit positions of di_bits / do_bits / adc slots).
DI = (
    "CONTACT",
    "LATCH_ENGAGED",
    "LATCH_HOME",
    "PLANE_EXTENDED",
    "PLANE_RETRACTED",
    "CONNECTOR_MATED",
    "SV_VALVE_OPEN",
    "TV_VALVE_OPEN",
    "LATCH_NOT_ENGAGED",
)
DO = ("LATCH_DIR", "LATCH_ENABLE", "PLANE_EXTEND", "PLANE_RETRACT", "SV_VALVE", "TV_VALVE")
ADC = ("SV_TANK", "TV_TANK", "LINE", "PLANE_POS", "CONTACT_FORCE")
RESET_CAUSES = ("UNKNOWN", "POWER_ON", "PIN", "WATCHDOG", "BROWNOUT", "SOFTWARE", "LOCKUP")


class LockstepError(RuntimeError):
    """The lockstep contract broke: lost/repeated frame, bad echo, step counts disagree."""


@dataclass(frozen=True)
class McuReply:
    magic: int
    version: int
    frame: int
    status: int
    expected_frame: int
    sim_time_ms: int
    uptime_ms: int
    do_bits: int
    do_any_bits: int
    steps_fwd: int
    steps_rev: int
    steps_total: int
    uart_tx_bytes: int
    uart_rx_pending: int
    resets: int
    reset_cause: int
    watchdog_kicks: int
    flags: int
    app_state: int
    valve_violation_ms: int
    fault_flags: int

    def do(self, name: str) -> bool:
        return bool(self.do_bits >> DO.index(name) & 1)

    def do_any(self, name: str) -> bool:
        return bool(self.do_any_bits >> DO.index(name) & 1)

    @property
    def step_timer_running(self) -> bool:
        return bool(self.flags & MCU_STEP_TIMER_RUNNING)


def encode_plant(
    frame: int,
    advance_ms: int,
    di_bits: int,
    adc_counts: list[int],
    adc_fail_bits: int = 0,
    flags: int = 0,
    uart_rx_bytes: int = 0,
    magic: int = PLANT_MAGIC,
) -> bytes:
    adc = [max(0, min(0xFFFF, int(c))) for c in adc_counts] + [0] * (ADC_SLOTS - len(adc_counts))
    return _PLANT.pack(
        magic, VERSION, frame, advance_ms, flags, di_bits, adc_fail_bits, uart_rx_bytes, *adc[:ADC_SLOTS]
    )


def decode_mcu(data: bytes) -> McuReply:
    if len(data) != _MCU.size:
        raise LockstepError(f"MCU reply of {len(data)} bytes, expected {_MCU.size}")
    return McuReply(**dict(zip(_MCU_FIELDS, _MCU.unpack(data), strict=True)))


class SimMcu:
    """The ``oibar_sim_mcu`` process: lockstep socket, pty slave (the host's serial port)."""

    def __init__(
        self,
        exe: Path,
        *,
        watchdog_ms: int | None = None,
        build_id: str = "rig",
        stderr_path: Path | None = None,
        reply_timeout_s: float = 10.0,
        flash_image: Path | None = None,
    ) -> None:
        """``flash_image``: keep the MCU's parameter flash (CMD_SAVE_PARAMS) in this file across
        processes (``--flash-image``); None: blank at start, the defaults, as every run before."""
        exe = Path(exe)
        if not exe.exists():
            raise FileNotFoundError(f"simulated MCU not found at {exe} (run `make firmware-host`)")
        self.pty_fd = -1  # the pseudo-terminal's descriptor once opened; -1: none (closed)
        self._sock, child = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        self._stderr = open(stderr_path, "wb") if stderr_path else subprocess.DEVNULL  # noqa: SIM115  (closed by close())
        self.proc = subprocess.Popen(
            [
                str(exe),
                "--lockstep-fd",
                str(child.fileno()),
                *(["--watchdog-ms", str(watchdog_ms)] if watchdog_ms is not None else []),
                "--build-id",
                build_id,
                *(["--flash-image", str(flash_image)] if flash_image is not None else []),
            ],
            pass_fds=(child.fileno(),),
            stdout=subprocess.PIPE,
            stderr=self._stderr,
        )
        child.close()
        assert self.proc.stdout is not None  # stdout=PIPE
        line = self.proc.stdout.readline().decode(errors="replace").strip()
        if not line.startswith("PTY "):
            self.close()
            raise LockstepError(f"unexpected first line from the simulated MCU: {line!r}")
        self.pty_path = line[4:]
        # The host's end of the UART, opened like a real serial port (raw, non-blocking).
        self.pty_fd = os.open(self.pty_path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
        tty.setraw(self.pty_fd)
        self.reply_timeout_s = reply_timeout_s
        self.frame = 0
        self.steps_seen = 0
        self.last: McuReply | None = None

    def send_raw(self, data: bytes) -> McuReply:
        """One raw exchange, no checks (the tests use it to break the protocol on purpose)."""
        self._sock.sendall(data)
        ready, _, _ = select.select([self._sock], [], [], self.reply_timeout_s)
        if not ready:
            raise LockstepError(f"no lockstep reply within {self.reply_timeout_s} s")
        return decode_mcu(self._sock.recv(256))

    def exchange(
        self,
        advance_ms: int,
        di_bits: int,
        adc_counts: list[int],
        *,
        adc_fail_bits: int = 0,
        flags: int = 0,
        uart_rx_bytes: int = 0,
    ) -> McuReply:
        """Run ``advance_ms`` of MCU time with these inputs; check the reply."""
        self.frame += 1
        reply = self.send_raw(
            encode_plant(self.frame, advance_ms, di_bits, adc_counts, adc_fail_bits, flags, uart_rx_bytes)
        )
        if reply.magic != MCU_MAGIC or reply.status != 0:
            raise LockstepError(
                f"MCU refused frame {self.frame}: {STATUS_NAMES.get(reply.status, reply.status)} "
                f"(it expected frame {reply.expected_frame})"
            )
        if reply.frame != self.frame:
            raise LockstepError(f"reply echoes frame {reply.frame}, sent {self.frame}")
        self.steps_seen += reply.steps_fwd + reply.steps_rev
        if reply.steps_total != self.steps_seen:
            raise LockstepError(
                f"step pulses: MCU counted {reply.steps_total}, plant received {self.steps_seen}"
            )
        self.last = reply
        return reply

    def read_uart(self, n: int, timeout_s: float = 2.0) -> bytes:
        """Exactly the ``n`` bytes the MCU reports it wrote (they may still be in the tty layer)."""
        out = bytearray()
        while len(out) < n:
            try:
                chunk = os.read(self.pty_fd, n - len(out))
            except BlockingIOError:
                chunk = b""
            if chunk:
                out += chunk
                continue
            ready, _, _ = select.select([self.pty_fd], [], [], timeout_s)
            if not ready:
                raise LockstepError(f"MCU wrote {n} UART bytes, only {len(out)} arrived")
        return bytes(out)

    def write_uart(self, data: bytes) -> int:
        done = 0
        while done < len(data):
            try:
                done += os.write(self.pty_fd, data[done:])
            except BlockingIOError:
                select.select([], [self.pty_fd], [], 1.0)
        return done

    def close(self) -> None:
        if self.proc.poll() is None:
            try:
                self.frame += 1
                self._sock.sendall(encode_plant(self.frame, 1, 0, [], flags=FLAG_QUIT))
                self.proc.wait(timeout=5)
            except (OSError, subprocess.TimeoutExpired):
                self.proc.kill()
                self.proc.wait()
        self._sock.close()
        if self.pty_fd >= 0:
            os.close(self.pty_fd)
            self.pty_fd = -1
        if self.proc.stdout:
            self.proc.stdout.close()
        if not isinstance(self._stderr, int):  # a file of ours, not subprocess.DEVNULL
            self._stderr.close()

    def __enter__(self) -> SimMcu:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
