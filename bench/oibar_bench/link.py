"""Figure 6: the host <-> MCU link. Round trips and throughput of the Python LinkClient against

- the C link layer in ``oibar_link_peer`` (build/fw-host) over a pseudo-terminal, and
- the STM32F405 image on QEMU's netduinoplus2 board, its USART1 on a loopback TCP socket;

and the 115200-baud budget computed from real encoded frames (oibar.pb + the framing code:
header byte, CRC-32C, COBS, delimiter; 10 bits per byte on the wire).
"""

from __future__ import annotations

import contextlib
import os
import shutil
import socket
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path

from .core import BUILD, Context, Result, Target, measurement, summarize_ms

BAUD = 115200
BITS_PER_BYTE = 10  # 8N1: start + 8 data + stop
TELEMETRY_HZ = 10.0  # telemetry_period 100 ms (docs/link.md)
HEARTBEAT_HZ = 5.0  # heartbeat_period 200 ms, each side
NAV_HZ = 10.0  # the navigation loop (SPEC: 10 Hz)
RETRANSMIT_TIMEOUT_MS = 200.0  # the host's default: a slower answer costs a retransmission

RTT_TARGET = Target("<=", RETRANSMIT_TIMEOUT_MS, "ms", "docs/link.md: answered before the host retransmits")
TELEMETRY_TARGET = Target(
    ">=", 0.95 * TELEMETRY_HZ, "Hz", "docs/link.md: telemetry every 100 ms (within 5 %)"
)
UTIL_TARGET = Target("<=", 50.0, "%", "ours: half the line free for retransmissions, events, parameters")

QEMU_BOOT_TIMEOUT_S = 20.0

LINK_COLUMNS = [
    ("link", "link"),
    ("what", "measured"),
    ("runs", "runs"),
    ("median_ms", "median (ms)"),
    ("p99_ms", "p99 (ms)"),
    ("rate", "rate (/s)"),
    ("target", "target"),
    ("gap", "gap"),
]


# ----------------------------------------------------------------------------- the two peers
def peer_path() -> Path:
    return Path(os.environ.get("OIBAR_FW_BUILD", BUILD / "fw-host")) / "link" / "oibar_link_peer"


@contextlib.contextmanager
def pty_peer() -> Iterator[str]:
    """Start oibar_link_peer; yield its pseudo-terminal's path."""
    exe = peer_path()
    if not exe.is_file():
        raise FileNotFoundError(f"{exe} is missing: run `make firmware-host`")
    proc = subprocess.Popen([str(exe)], stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    try:
        banner = proc.stdout.readline().strip()
        if not banner.startswith("PTY "):
            raise RuntimeError(f"oibar_link_peer printed {banner!r}, expected 'PTY <path>'")
        yield banner.split(" ", 1)[1]
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=3)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def _free_tcp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@contextlib.contextmanager
def qemu_board(log: Path) -> Iterator[str]:
    """Boot the STM32F405 image on qemu-system-arm (netduinoplus2); yield the pyserial URL of its
    USART1 (a TCP server socket QEMU listens on)."""
    qemu = shutil.which("qemu-system-arm")
    if qemu is None:
        raise FileNotFoundError("qemu-system-arm is not installed: run `make setup`")
    image = BUILD / "fw-arm-qemu" / "oibar_stm32f4.elf"
    if not image.is_file():
        raise FileNotFoundError(f"{image} is missing: run `make firmware-arm-qemu`")
    port = _free_tcp_port()
    # nodelay=on: no Nagle on QEMU's side, or each byte-by-byte UART reply waits for a delayed ACK.
    chardev = f"socket,id=link,host=127.0.0.1,port={port},server=on,wait=off,nodelay=on"
    cmd = [
        qemu,
        "-M",
        "netduinoplus2",
        "-nographic",
        "-monitor",
        "none",
        "-no-reboot",
        "-kernel",
        str(image),
        "-chardev",
        chardev,
        "-serial",
        "chardev:link",
    ]
    with open(log, "wb") as fh:
        proc = subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stdout=fh, stderr=subprocess.STDOUT)
    try:
        deadline = time.monotonic() + QEMU_BOOT_TIMEOUT_S
        while True:
            if proc.poll() is not None:
                raise RuntimeError(
                    f"QEMU exited ({proc.returncode}): {log.read_text(errors='replace')[-1000:]}"
                )
            # QEMU listens with wait=off; this probe connection is closed at once and the
            # chardev waits for the next client.
            with contextlib.suppress(OSError), socket.create_connection(("127.0.0.1", port), timeout=0.5):
                break
            if time.monotonic() > deadline:
                raise RuntimeError(f"QEMU did not open its serial socket in {QEMU_BOOT_TIMEOUT_S:.0f} s")
            time.sleep(0.1)
        yield f"socket://127.0.0.1:{port}"
    finally:
        if proc.poll() is None:
            proc.kill()
        proc.wait(timeout=10)


def _connect(url: str, arrivals: list[tuple[float, int]], timeout_s: float):
    """A connected LinkClient (retrying the handshake while the peer boots)."""
    from oibar.link import LinkClient
    from oibar.link.errors import LinkError

    deadline = time.monotonic() + timeout_s
    while True:
        client = LinkClient(
            url,
            retransmit_timeout_s=0.5,
            max_retries=4,
            on_telemetry=lambda tm: arrivals.append((time.monotonic(), tm.uptime_ms)),
        )
        try:
            client.connect()
            return client
        except LinkError as exc:
            client.close()
            if time.monotonic() > deadline:
                raise RuntimeError(f"no handshake with {url} in {timeout_s:.0f} s: {exc}") from exc
            time.sleep(0.3)


def measure(ctx: Context, url: str, label: str, param_id: int) -> tuple[list[dict], dict]:
    """RTT of NOOP commands and parameter reads, command throughput, telemetry rate and jitter."""
    n = 40 if ctx.quick else 400
    tele_s = 1.5 if ctx.quick else 6.0
    arrivals: list[tuple[float, int]] = []  # (host time s, the MCU's uptime_ms) per Telemetry
    client = _connect(url, arrivals, QEMU_BOOT_TIMEOUT_S)
    rows = []
    extra = {}
    try:
        for what, call in (
            ("command NOOP -> Ack", lambda: client.command("NOOP")),
            (f"ParamGet({param_id}) -> ParamValue", lambda: client.param_get(param_id)),
        ):
            call()  # warm-up (first request after the handshake)
            lat = []
            t_all = time.perf_counter()
            for _ in range(n):
                t0 = time.perf_counter()
                r = call()
                lat.append((time.perf_counter() - t0) * 1e3)
                ok = r.accepted if hasattr(r, "accepted") else r.ok
                if not ok:
                    raise RuntimeError(f"{label}: {what} refused ({r.reason})")
            total_s = time.perf_counter() - t_all
            s = summarize_ms(lat)
            rows.append(
                {
                    "link": label,
                    "what": f"{what} round trip (stop and wait)",
                    **{k: s[k] for k in ("runs", "median_ms", "p99_ms", "max_ms")},
                    "rate": n / total_s,
                    "target": RTT_TARGET,
                    "measured": s["p99_ms"],
                }
            )
            ctx.progress(
                f"link {label} {what}: median {s['median_ms']:.2f} ms, p99 {s['p99_ms']:.2f} ms, "
                f"{n / total_s:.0f} requests/s"
            )
        arrivals.clear()
        time.sleep(tele_s)
        got = list(arrivals)
        ts = [t for t, _ in got]
        if len(ts) < 3:
            raise RuntimeError(f"{label}: only {len(ts)} telemetry packets in {tele_s} s")
        gaps = [(b - a) * 1e3 for a, b in zip(ts, ts[1:], strict=False)]
        s = summarize_ms(gaps)
        hz = (len(ts) - 1) / (ts[-1] - ts[0])
        rows.append(
            {
                "link": label,
                "what": "telemetry period (MCU -> host)",
                **{k: s[k] for k in ("runs", "median_ms", "p99_ms", "max_ms")},
                "rate": hz,
                "target": TELEMETRY_TARGET,
                "measured": hz,
            }
        )
        # The MCU's clock against the host's over the same window: an emulated board that gets
        # less CPU than it needs counts fewer ticks, and its periodic traffic slows with it.
        extra["mcu_clock_ratio"] = (got[-1][1] - got[0][1]) / 1e3 / (ts[-1] - ts[0])
        ctx.progress(
            f"link {label} telemetry: {hz:.2f} Hz, period p99 {s['p99_ms']:.1f} ms, MCU clock "
            f"{100 * extra['mcu_clock_ratio']:.1f} % of real time"
        )
        tm = client.telemetry
        if tm is not None:
            extra["telemetry_frame_B"] = len(_frame_of("telemetry", tm))
        st = client.statistics
        extra["retransmissions"] = st.retransmissions
        extra["timeouts"] = st.timeouts
    finally:
        client.close()
    return rows, extra


def _packet(body: str, msg, seq: int = 1):
    from oibar import pb

    p = pb.Packet(seq=seq)
    getattr(p, body).CopyFrom(msg)
    return p


def _frame_of(body: str, msg, seq: int = 1) -> bytes:
    from oibar.link.framing import encode_frame

    return encode_frame(_packet(body, msg, seq))


@measurement(
    "link.pty", "Python LinkClient <-> C link peer (oibar_link_peer) over a pseudo-terminal", LINK_COLUMNS
)
def over_pty(ctx: Context) -> Result:
    with pty_peer() as pty:
        ctx.progress(f"link pty: peer on {pty}")
        rows, extra = measure(ctx, pty, "pty", param_id=2)
    notes = [
        "The peer runs the firmware's C link layer (ASan+UBSan build) with a minimal application; a "
        "pseudo-terminal does not pace bytes at 115200 baud, so these are the software's round trips "
        "(see the budget below for the time on the wire). Requests are stop and wait: one outstanding."
    ]
    if extra:
        notes.append(
            f"Client counters after the run: {extra.get('retransmissions', 0)} retransmissions, "
            f"{extra.get('timeouts', 0)} timeouts."
        )
    ctx.shared["pty_extra"] = extra
    return Result(rows, notes)


@measurement(
    "link.qemu", "Python LinkClient <-> the STM32F405 image on QEMU (USART1 on a TCP socket)", LINK_COLUMNS
)
def over_qemu(ctx: Context) -> Result:
    with qemu_board(ctx.tmp / "qemu.log") as url:
        ctx.progress(f"link qemu: board up, USART1 at {url}")
        rows, extra = measure(ctx, url, "QEMU", param_id=1)
    for r in rows:
        r["link"] = "QEMU netduinoplus2"
    notes = [
        "The emulator image (build/fw-arm-qemu, OIBAR_QEMU=ON) under qemu-system-arm; the emulated "
        "board has no ADC, so the firmware sits in STATE_FAULT (tests/qemu): NOOP is still accepted "
        "and parameters read, which is what is timed. "
        "QEMU's USART does not pace bytes at 115200 baud either, and its CPU is emulated, not timed. The "
        "chardev socket has nodelay=on: with Nagle's algorithm the firmware's byte-by-byte UART output "
        "waits for the host's delayed ACKs and every round trip costs ~40 ms of TCP, not firmware."
    ]
    if extra:
        notes.append(
            f"Client counters after the run: {extra.get('retransmissions', 0)} retransmissions, "
            f"{extra.get('timeouts', 0)} timeouts. The board's own Telemetry re-encodes to "
            f"{extra.get('telemetry_frame_B', '?')} bytes on the wire."
        )
        if "mcu_clock_ratio" in extra:
            notes.append(
                f"The emulated board's clock (Telemetry.uptime_ms) advanced at "
                f"{100 * extra['mcu_clock_ratio']:.1f} % of real time during the telemetry window: the "
                "firmware counts SysTick interrupts, and a board that gets less host CPU than it needs "
                "counts fewer, so its telemetry rate drops by as much (an emulation effect; the pty row "
                "shows the link code keeps the period)."
            )
    return Result(rows, notes)


# ----------------------------------------------------------------------------- budget
def typical_messages() -> dict:
    """A Telemetry, NavUpdate and Heartbeats with the values of a transfer one hour into a mission:
    large counters and non-zero floats cost the most bytes."""
    from oibar import pb

    tm = pb.Telemetry(
        uptime_ms=3_600_000,
        state=pb.STATE_TRANSFERRING,
        fault_flags=0,
        latch_pos_steps=650,
        latch_engaged=True,
        plane_pos_mm=39.96,
        contact=True,
        connector_mated=True,
        sv_valve_cmd_open=True,
        sv_valve_open=True,
        tv_valve_cmd_open=True,
        tv_valve_open=True,
        sv_tank_kpa=2151.7,
        tv_tank_kpa=812.4,
        line_kpa=1003.9,
        target_pressure_kpa=1200.0,
        event_queue_overflows=0,
        host_link_alive=True,
    )
    tm.link.rx_packets, tm.link.tx_packets = 54_000, 54_321
    tm.link.rx_crc_errors, tm.link.rx_framing_errors, tm.link.rx_duplicates = 3, 2, 1
    nav = pb.NavUpdate(
        frame_id=36_000,
        stamp_ms=3_600_000,
        range_m=2.451,
        closing_speed_mps=0.0298,
        phase=pb.NAV_PHASE_SOFT_DOCK,
        confidence=0.93,
    )
    nav.t_cam_target_m.x, nav.t_cam_target_m.y, nav.t_cam_target_m.z = 0.0123, -0.0345, 2.4871
    nav.q_cam_target.w, nav.q_cam_target.x, nav.q_cam_target.y, nav.q_cam_target.z = (
        0.9997,
        0.0102,
        -0.0201,
        0.0049,
    )
    hb = pb.Heartbeat(uptime_ms=3_600_000)
    cmd = pb.Command(opcode=pb.CMD_START_TRANSFER, target_pressure_kpa=1200.0)
    ack = pb.Ack(accepted=True, state=pb.STATE_TRANSFERRING)
    return {"telemetry": tm, "nav_update": nav, "heartbeat": hb, "command": cmd, "ack": ack}


BUDGET_COLUMNS = [
    ("direction", "direction"),
    ("message", "message"),
    ("rate_hz", "rate (Hz)"),
    ("packet_B", "packet (bytes)"),
    ("frame_B", "on the wire (bytes)"),
    ("bps", "bits/s"),
    ("util_pct", "of 115200 baud (%)"),
    ("target", "target"),
    ("gap", "gap"),
]


@measurement("link.budget", "115200-baud budget from real encoded frames (steady state)", BUDGET_COLUMNS)
def budget(ctx: Context) -> Result:
    msgs = typical_messages()
    seq = 54_000  # a seq an hour into the mission: 3 varint bytes, as then
    sizes = {}
    for body, msg in msgs.items():
        sizes[body] = (len(_packet(body, msg, seq).SerializeToString()), len(_frame_of(body, msg, seq)))
    flows = {
        "MCU -> host": [("Telemetry", "telemetry", TELEMETRY_HZ), ("Heartbeat", "heartbeat", HEARTBEAT_HZ)],
        "host -> MCU": [("NavUpdate", "nav_update", NAV_HZ), ("Heartbeat", "heartbeat", HEARTBEAT_HZ)],
    }
    rows = []
    for direction, items in flows.items():
        total = 0.0
        for name, body, hz in items:
            packet_b, frame_b = sizes[body]
            bps = hz * frame_b * BITS_PER_BYTE
            total += bps
            rows.append(
                {
                    "direction": direction,
                    "message": name,
                    "rate_hz": hz,
                    "packet_B": packet_b,
                    "frame_B": frame_b,
                    "bps": bps,
                    "util_pct": 100.0 * bps / BAUD,
                }
            )
        rows.append(
            {
                "direction": direction,
                "message": "**total**",
                "bps": total,
                "util_pct": 100.0 * total / BAUD,
                "target": UTIL_TARGET,
                "measured": 100.0 * total / BAUD,
            }
        )
    wire_ms = (sizes["command"][1] + sizes["ack"][1]) * BITS_PER_BYTE / BAUD * 1e3
    notes = [
        "Frames are encoded by the host's own code (oibar.pb + oibar.link.framing.encode_frame): packet + "
        "1 header byte + 4 CRC-32C bytes, COBS (+1 byte per started 254), 0x00 delimiter; the UART is full "
        "duplex, so each direction has the whole 115200 baud (11,520 bytes/s at 10 bits per byte).",
        "Typical values: a transfer one hour into a mission (STATE_TRANSFERRING, pressures, link counters in the "
        "tens of thousands, seq 54,000); events, commands and parameter traffic are occasional and not in the "
        f"steady state. A command and its Ack ({sizes['command'][1]} + {sizes['ack'][1]} bytes) spend "
        f"{wire_ms:.1f} ms on the wire at 115200 baud, on top of the round trips above.",
    ]
    extra = ctx.shared.get("pty_extra") or {}
    if "telemetry_frame_B" in extra:
        notes.append(
            f"For comparison, the link peer's own (link-only) Telemetry is {extra['telemetry_frame_B']} bytes "
            "on the wire."
        )
    ctx.progress(
        "link budget: "
        + ", ".join(f"{r['direction']} {r['util_pct']:.1f} %" for r in rows if r["message"] == "**total**")
    )
    return Result(rows, notes)
