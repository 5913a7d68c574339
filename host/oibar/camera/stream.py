"""Camera frames over a local TCP socket: ``--camera frames+tcp://127.0.0.1:PORT``.

For a camera the daemon cannot open itself (a vendor SDK, a GStreamer pipeline, another
process that owns the device, or the HIL rig's renderer in ``make sitl``): that process runs a
:class:`FrameStreamServer` (or anything speaking the same format) and ``oibar nav`` connects to
it with :class:`FrameStreamSource`. Loopback is the intended use; the format has no
authentication.

Wire format, per frame (little endian)::

    magic   4 bytes  b"OIBF"
    version u16      1
    flags   u16      0
    width   u32      pixels
    height  u32      pixels
    t_s     f64      capture time on the sender's monotonic clock (strictly increasing)
    pixels  width * height * 3 bytes, RGB8, row-major

A connection that closes, or is silent for ``lost_timeout_s``, is a lost camera
(:class:`CameraLost`): the daemon reconnects every ``camera_retry_s``. A malformed header is a
lost camera too (the stream cannot be resynchronised).
"""

from __future__ import annotations

import socket
import struct
import threading

import numpy as np

from oibar.camera.errors import CameraLost, CameraOpenError
from oibar.camera.sources import CameraSource

MAGIC = b"OIBF"
VERSION = 1
HEADER = struct.Struct("<4sHHIId")
MAX_PIXELS = 4096 * 4096
SCHEME = "frames+tcp://"


def encode_frame_header(width: int, height: int, t_s: float) -> bytes:
    return HEADER.pack(MAGIC, VERSION, 0, width, height, float(t_s))


def parse_address(spec: str) -> tuple[str, int]:
    hostport = spec[len(SCHEME) :] if spec.startswith(SCHEME) else spec
    host, sep, port = hostport.rpartition(":")
    if not sep or not port.isdigit():
        raise CameraOpenError(f"{spec!r}: expected {SCHEME}HOST:PORT")
    return host or "127.0.0.1", int(port)


class FrameStreamSource(CameraSource):
    """Frames from a :class:`FrameStreamServer` (or a compatible sender)."""

    def __init__(self, spec: str, *, lost_timeout_s: float = 1.0, connect_timeout_s: float = 2.0) -> None:
        super().__init__()
        self.host, self.port = parse_address(spec)
        self.name = f"{SCHEME}{self.host}:{self.port}"
        self.lost_timeout_s = float(lost_timeout_s)
        self.connect_timeout_s = float(connect_timeout_s)
        self._sock: socket.socket | None = None

    def _open(self) -> None:
        try:
            self._sock = socket.create_connection((self.host, self.port), timeout=self.connect_timeout_s)
        except OSError as exc:
            raise CameraOpenError(f"{self.name}: cannot connect ({exc})") from exc
        self._sock.settimeout(self.lost_timeout_s)

    def _recv_exact(self, n: int) -> bytes:
        buf = bytearray()
        sock = self._sock
        assert sock is not None, "read before open"  # the base class opens before it reads
        while len(buf) < n:
            try:
                chunk = sock.recv(n - len(buf))
            except TimeoutError:
                raise CameraLost(
                    f"{self.name}: no frame for {self.lost_timeout_s:.1f} s",
                    seconds_without_frame=self.lost_timeout_s,
                ) from None
            except OSError as exc:
                raise CameraLost(f"{self.name}: {exc}") from exc
            if not chunk:
                raise CameraLost(f"{self.name}: the sender closed the stream")
            buf += chunk
        return bytes(buf)

    def _read(self) -> tuple[np.ndarray, float]:
        if self._sock is None:
            raise CameraLost(f"{self.name}: not connected")
        magic, version, _flags, w, h, t_s = HEADER.unpack(self._recv_exact(HEADER.size))
        if magic != MAGIC or version != VERSION or not (0 < w * h <= MAX_PIXELS):
            raise CameraLost(
                f"{self.name}: malformed frame header (magic {magic!r}, version {version}, {w}x{h})"
            )
        pixels = self._recv_exact(w * h * 3)
        return np.frombuffer(pixels, dtype=np.uint8).reshape(h, w, 3), t_s

    def _close(self) -> None:
        if self._sock is not None:
            try:
                self._sock.close()
            finally:
                self._sock = None


class FrameStreamServer:
    """Serves frames to the connected clients (the newest client wins; a slow or gone client is
    dropped, never waited for). ``FrameStreamServer(port=0)`` picks a free loopback port."""

    def __init__(self, host: str = "127.0.0.1", port: int = 0, send_timeout_s: float = 0.5) -> None:
        self._listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self._listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self._listener.bind((host, port))
        self._listener.listen(2)
        self._listener.settimeout(0.2)
        self.host, self.port = self._listener.getsockname()[:2]
        self.send_timeout_s = send_timeout_s
        self._client: socket.socket | None = None
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self.frames_sent = 0
        self.clients = 0
        self._thread = threading.Thread(target=self._accept, name="frame-stream-accept", daemon=True)
        self._thread.start()

    @property
    def url(self) -> str:
        return f"{SCHEME}{self.host}:{self.port}"

    @property
    def connected(self) -> bool:
        with self._lock:
            return self._client is not None

    def _accept(self) -> None:
        while not self._stop.is_set():
            try:
                conn, _ = self._listener.accept()
            except (TimeoutError, OSError):
                continue
            conn.settimeout(self.send_timeout_s)
            with self._lock:
                old, self._client = self._client, conn
                self.clients += 1
            if old is not None:
                old.close()

    def send(self, image: np.ndarray, t_s: float) -> bool:
        """Send one RGB8 frame to the client; False when there is none (or it just went)."""
        img = np.ascontiguousarray(image, dtype=np.uint8)
        h, w = img.shape[:2]
        data = encode_frame_header(w, h, t_s) + img.tobytes()
        with self._lock:
            conn = self._client
        if conn is None:
            return False
        try:
            conn.sendall(data)
        except OSError:
            self.disconnect(conn)
            return False
        self.frames_sent += 1
        return True

    def disconnect(self, conn: socket.socket | None = None) -> None:
        """Drop the client (it reconnects if it wants to): the rig's "camera unplugged"."""
        with self._lock:
            if conn is None or conn is self._client:
                conn, self._client = self._client, None
            else:
                conn = None
        if conn is not None:
            conn.close()

    def close(self) -> None:
        self._stop.set()
        self.disconnect()
        self._listener.close()
        self._thread.join(1.0)
