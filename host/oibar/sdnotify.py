"""systemd's service notifications (sd_notify) without a library: a few datagrams on the socket
named by $NOTIFY_SOCKET (deploy/systemd/oibar-nav.service, Type=notify, WatchdogSec=).

``READY=1`` once start-up is over (model loaded, camera checked, link opening), ``WATCHDOG=1``
from the navigation loop itself (a hung loop stops petting and systemd restarts the service),
``STOPPING=1`` on the way out. Without $NOTIFY_SOCKET (not under systemd) every call does
nothing. A notification that cannot be sent is dropped: it must never stop the daemon.
"""

from __future__ import annotations

import os
import socket
import time


class Notifier:
    def __init__(self, environ: dict[str, str] | None = None) -> None:
        env = os.environ if environ is None else environ
        addr = env.get("NOTIFY_SOCKET", "")
        # an abstract socket is written with a leading '@'
        self.address = "\0" + addr[1:] if addr.startswith("@") else addr
        # the watchdog is ours when WATCHDOG_USEC is set and WATCHDOG_PID (if given) is us
        usec = env.get("WATCHDOG_USEC", "")
        pid = env.get("WATCHDOG_PID", "")
        mine = not pid or pid == str(os.getpid())
        self.watchdog_s = int(usec) / 1e6 if usec.isdigit() and int(usec) > 0 and mine else None
        self._last_pet = -1e18
        self._sock: socket.socket | None = None

    @property
    def enabled(self) -> bool:
        return bool(self.address)

    def send(self, *fields: str) -> bool:
        """One notification of ``KEY=VALUE`` fields; True when it was sent."""
        if not self.address:
            return False
        try:
            if self._sock is None:
                self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
            self._sock.sendto("\n".join(fields).encode(), self.address)
            return True
        except OSError:
            return False

    def ready(self, status: str = "") -> bool:
        return self.send("READY=1", *_status(status))

    def watchdog(self, status: str = "") -> bool:
        """Pet the watchdog, at most every half period (systemd's advice); with its status line."""
        if self.watchdog_s is None:
            return False
        now = time.monotonic()
        if now - self._last_pet < self.watchdog_s / 2:
            return False
        self._last_pet = now
        return self.send("WATCHDOG=1", *_status(status))

    def stopping(self, status: str = "") -> bool:
        return self.send("STOPPING=1", *_status(status))

    def close(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None


def _status(text: str) -> list[str]:
    """A STATUS= field on one line (systemctl status shows it), runs of spaces collapsed."""
    line = " ".join(text.split())
    return [f"STATUS={line}"] if line else []
