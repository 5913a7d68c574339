"""The ``oibar`` command line.

``oibar link`` is the first thing to run against a new board or cable: it proves the link
works end to end (handshake, commands, telemetry) and shows its health live. Expected
failures (no port, no answer, wrong firmware version) end with one readable line and exit
code 2, never a traceback.
"""

from __future__ import annotations

import argparse
import logging
import signal
import sys
import threading
import time
from collections.abc import Sequence
from typing import TYPE_CHECKING, TextIO

if TYPE_CHECKING:
    from oibar.link.client import LinkClient

# The schema and the link are imported inside main() with Ctrl-C deferred: importing
# protobuf takes a noticeable moment, and a KeyboardInterrupt raised inside its C extension's
# initialisation can crash the interpreter instead of just printing a traceback.

EXIT_OK = 0
EXIT_ERROR = 2
EXIT_INTERRUPTED = 130

_LINK_EPILOG = """\
examples:
  oibar link --port /dev/ttyACM0
  oibar link --port /dev/ttyUSB0 --command NOOP APPROACH_ARM --seconds 10
  oibar link --port socket://127.0.0.1:5555 --command START_TRANSFER --target-pressure-kpa 1200

commands (the CMD_ prefix is optional, any case):
  {known_commands}

exit status: 0 when the link worked (a refused command is reported, not an error),
2 when the port cannot be opened, the MCU does not answer or speaks another protocol
version, or the configuration file (--config) is invalid, 130 on Ctrl-C.
"""


class _VersionAction(argparse.Action):
    """``--version``: the package, link protocol and default model versions (the model's metadata
    is read only when asked)."""

    def __init__(self, option_strings: Sequence[str], dest: str, help: str | None = None) -> None:
        super().__init__(option_strings, dest, nargs=0, default=argparse.SUPPRESS, help=help)

    def __call__(self, parser: argparse.ArgumentParser, *args: object) -> None:
        from oibar.resources import version_text

        print(version_text())
        parser.exit()


def build_parser() -> argparse.ArgumentParser:
    from oibar import argtypes, pb

    known_commands = " ".join(n[4:] for n in pb.CommandOpcode.keys() if n != "CMD_UNSPECIFIED")  # noqa: SIM118
    parser = argparse.ArgumentParser(
        prog="oibar",
        description="OIBAR companion-computer tools (docking and refuelling mechanism).",
    )
    parser.add_argument(
        "--version",
        action=_VersionAction,
        help="print the package, link protocol and model versions and exit",
    )
    parser.add_argument(
        "-v",
        "--verbose",
        action="count",
        default=0,
        help="log more: -v for link events, -vv for every retransmission",
    )
    sub = parser.add_subparsers(dest="subcommand", metavar="SUBCOMMAND")
    link = sub.add_parser(
        "link",
        help="connect to the MCU, send commands, watch the link status",
        description=(
            "Open the link to the MCU and print its handshake (firmware, build, protocol\n"
            "version, reset cause); send the given mechanism commands in order and print\n"
            "each answer; then show a live status line (state, MCU uptime, telemetry rate,\n"
            "link counters) for --seconds."
        ),
        epilog=_LINK_EPILOG.format(known_commands=known_commands),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    link.add_argument(
        "--port",
        required=True,
        metavar="URL",
        help="serial device (/dev/ttyACM0, COM3), socket://HOST:PORT or loop://",
    )
    link.add_argument(
        "--baudrate", type=argtypes.positive_int(), default=115200, help="serial baud rate (default: 115200)"
    )
    link.add_argument(
        "--seconds",
        type=argtypes.number(0.0, 86400.0),
        default=5.0,
        metavar="S",
        help="how long to show the live status, in seconds (default: 5; 0 skips it)",
    )
    link.add_argument(
        "--command",
        dest="commands",
        nargs="+",
        action="extend",
        default=[],
        metavar="NAME",
        help="mechanism command(s) to send after connecting, e.g. NOOP APPROACH_ARM",
    )
    link.add_argument(
        "--target-pressure-kpa",
        type=argtypes.positive(10000.0),
        default=None,
        metavar="KPA",
        help="target pressure sent with the commands (used by START_TRANSFER)",
    )
    from oibar.calib.cli import register as register_calib
    from oibar.camera.calibrate import register as register_calibrate_camera
    from oibar.nav.cli import register as register_nav

    register_calib(sub)
    register_calibrate_camera(sub)
    register_nav(sub)
    _add_config_options(parser)
    return parser


def _add_config_options(parser: argparse.ArgumentParser) -> None:
    """``--config FILE`` on the top level and on every subcommand (oibar.config)."""
    from oibar.config import add_config_option, subparsers

    add_config_option(parser)
    for child in subparsers(parser).values():
        _add_config_options(child)


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``oibar`` console script; returns the exit status."""
    try:
        if not _import_link_modules():
            raise KeyboardInterrupt
        return _main(argv)
    except KeyboardInterrupt:
        print(file=sys.stderr)
        _error("interrupted")
        return EXIT_INTERRUPTED


def _import_link_modules() -> bool:
    """Import protobuf and the link with SIGINT held back; False if Ctrl-C was pressed."""
    if threading.current_thread() is not threading.main_thread():
        import oibar.link  # noqa: F401  (signal handlers can only be set in the main thread)

        return True
    pressed: list[int] = []
    previous = signal.signal(signal.SIGINT, lambda signum, frame: pressed.append(signum))
    try:
        import oibar.link  # noqa: F401
    finally:
        signal.signal(signal.SIGINT, previous)
    return not pressed


def _main(argv: Sequence[str] | None) -> int:
    from oibar.config import ConfigError, apply, config_from_argv, find_config
    from oibar.link.results import parse_opcode

    parser = build_parser()
    argv = list(sys.argv[1:] if argv is None else argv)
    try:
        config = find_config(argv)
        if config is not None:
            apply(parser, config)
    except ConfigError as exc:
        _error(f"configuration: {exc}")
        return EXIT_ERROR
    args = parser.parse_args(argv)
    if getattr(args, "config", None) != config_from_argv(argv):
        # argparse took an abbreviation (--conf FILE) that the file search above did not see
        parser.error("write --config in full")
    logging.basicConfig(
        level=max(logging.DEBUG, logging.WARNING - 10 * args.verbose),
        format="%(levelname)s %(name)s: %(message)s",
    )
    if args.subcommand is None:
        parser.print_help(sys.stderr)
        return EXIT_ERROR
    if hasattr(args, "handler"):  # subcommand groups registered from their own modules
        from oibar.calib.cli import run

        return getattr(args, "run", run)(args)
    if args.subcommand == "link":
        try:
            opcodes = [parse_opcode(name) for name in args.commands]
        except ValueError as exc:
            parser.error(str(exc))  # exits with 2
        return run_link(args.port, args.baudrate, args.seconds, opcodes, args.target_pressure_kpa)
    parser.error(f"unknown subcommand {args.subcommand!r}")
    return EXIT_ERROR  # not reached


def run_link(
    url: str,
    baudrate: int,
    seconds: float,
    opcodes: Sequence[int],
    target_pressure_kpa: float | None = None,
    out: TextIO | None = None,
) -> int:
    """Body of ``oibar link``; returns the exit status."""
    from oibar import pb
    from oibar.link.client import LinkClient
    from oibar.link.errors import LinkError, LinkTimeout, PortError, ProtocolVersionError

    out = out or sys.stdout
    client = LinkClient(url, baudrate=baudrate)
    try:
        info = client.connect()
        print(
            f"connected to {url}: firmware {info.firmware_version or '?'} "
            f"(build {info.build_id or '?'}), protocol {info.protocol_version}, "
            f"reset cause {info.reset_cause}, MCU uptime {info.uptime_ms / 1000:.1f} s",
            file=out,
            flush=True,
        )
        for opcode in opcodes:
            name = pb.enum_name(pb.CommandOpcode, opcode)
            result = client.command(opcode, target_pressure_kpa)
            verdict = "accepted" if result.accepted else "REFUSED"
            print(f"{name}: {verdict}, reason {result.reason}, state {result.state}", file=out, flush=True)
        _show_status(client, seconds, out)
        return EXIT_OK
    except PortError as exc:
        _error(str(exc))
    except ProtocolVersionError as exc:
        _error(str(exc))
    except LinkTimeout as exc:
        _error(f"no answer from the MCU on {url}: {exc}; is the firmware running, is the baud rate right?")
    except LinkError as exc:
        _error(str(exc))
    finally:
        try:
            client.close()
        except KeyboardInterrupt:  # a second Ctrl-C while closing: still no traceback
            pass
    return EXIT_ERROR


def _show_status(client: LinkClient, seconds: float, out: TextIO) -> None:
    """One status line, redrawn in place on a terminal, printed once a second otherwise."""
    if seconds <= 0:
        return
    from oibar.progress import StatusLine

    status = StatusLine(out, period_s=1.0)
    refresh_s = 0.25 if status.tty else 1.0
    start = time.monotonic()
    end = start + seconds
    while True:
        now = time.monotonic()
        status.show(status_line(client, now - start), force=True)
        if now >= end:
            break
        time.sleep(min(refresh_s, max(0.0, end - now)))
    status.end()


def status_line(client: LinkClient, elapsed_s: float) -> str:
    """State, MCU uptime, telemetry rate and link counters in one line; counters that
    signal trouble are listed only when non-zero, to keep it short."""
    from oibar import pb

    telemetry = client.telemetry
    stats = client.statistics
    state = pb.enum_name(pb.State, telemetry.state) if telemetry is not None else "state ?"
    uptime = f"{telemetry.uptime_ms / 1000:.1f} s" if telemetry is not None else "?"
    trouble = {
        "crc": stats.rx_crc_errors,
        "framing": stats.rx_framing_errors,
        "oversize": stats.rx_oversize,
        "bad header": stats.rx_bad_header,
        "undecodable": stats.rx_decode_errors,
        "unknown type": stats.rx_unknown_type,
        "lost": stats.lost_peer_packets,
        "retransmissions": stats.retransmissions,
        "timeouts": stats.timeouts,
        "reconnects": stats.reconnects,
    }
    problems = ", ".join(f"{name} {count}" for name, count in trouble.items() if count)
    return (
        f"[{elapsed_s:5.1f} s] link {'UP' if client.link_alive else 'DOWN'} | {state} | "
        f"MCU uptime {uptime} | telemetry {client.telemetry_rate_hz:4.1f} Hz | "
        f"rx {stats.rx_packets} tx {stats.tx_packets} | {problems or 'no errors'}"
    )


def _error(message: str) -> None:
    print(f"oibar: error: {message}", file=sys.stderr, flush=True)


if __name__ == "__main__":
    sys.exit(main())
