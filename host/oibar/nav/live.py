"""``oibar nav --live``: the flight log's channels served while it flies, over the Foxglove SDK's
WebSocket server (the Foxglove WebSocket protocol, subprotocol ``foxglove.sdk.v1``), for the Foxglove app's "Open
connection" -> "Foxglove WebSocket" -> ``ws://HOST:PORT``.

The channels are those of the MCAP file (oibar.nav.flightlog.CHANNELS): the camera image with the
fixture's outline over it (an Image panel on ``/camera/image`` with ``/camera/calibration``, the
``/nav/fixture`` scene and the ``/tf`` transforms), the pose, the filter, guidance and the MCU
link. The server has no authentication: it binds to loopback unless told otherwise
(``--live 0.0.0.0:8765`` serves the ground network).
"""

from __future__ import annotations

from typing import Any

DEFAULT_HOST = "127.0.0.1"
DEFAULT_PORT = 8765  # Foxglove's default


class LiveError(ValueError):
    """A ``--live`` address that cannot be used."""


def parse_address(spec: str) -> tuple[str, int]:
    """``PORT``, ``HOST:PORT`` or ``HOST`` -> (host, port); port 0 picks a free one."""
    spec = spec.strip()
    host, port_text = DEFAULT_HOST, str(DEFAULT_PORT)
    if spec.isdigit():
        port_text = spec
    elif spec.startswith("[") and "]" in spec:  # [::1]:8765
        host, _, rest = spec[1:].partition("]")
        if rest:
            port_text = rest.removeprefix(":")
    elif spec.count(":") == 1:
        host, port_text = spec.split(":")
    elif spec:
        host = spec
    if not host or not port_text.isdigit() or not 0 <= int(port_text) <= 65535:
        raise LiveError(f"--live {spec!r}: expected PORT, HOST:PORT or HOST (port 0-65535)")
    return host, int(port_text)


class LiveServer:
    """The SDK's WebSocket server on a logging context: every channel of the context is offered
    to each client that connects."""

    def __init__(self, context: Any, host: str = DEFAULT_HOST, port: int = DEFAULT_PORT) -> None:
        import foxglove

        try:
            self.server = foxglove.start_server(name="oibar nav", host=host, port=port, context=context)
        except Exception as exc:  # the SDK raises its own error for a port in use
            raise OSError(f"--live {host}:{port}: cannot serve ({exc})") from exc
        self.host = host
        self.port = int(self.server.port)

    @property
    def url(self) -> str:
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"ws://{host}:{self.port}"

    def stop(self) -> None:
        try:
            self.server.stop()
        except Exception:
            pass
