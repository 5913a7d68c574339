"""Frames over a local TCP socket (oibar.camera.stream): what `make sitl` feeds `oibar nav` with,
and what a user's own camera bridge can speak."""

import time

import numpy as np
import pytest

from oibar.camera import CameraLost, LatestFrame, open_source
from oibar.camera.stream import FrameStreamServer, FrameStreamSource


def wait_for(pred, timeout_s=2.0):
    t_end = time.monotonic() + timeout_s
    while time.monotonic() < t_end:
        if pred():
            return True
        time.sleep(0.01)
    return False


def test_frames_round_trip_and_a_closed_stream_is_a_lost_camera():
    server = FrameStreamServer()
    try:
        src = open_source(server.url)
        assert isinstance(src, FrameStreamSource)
        src.lost_timeout_s = 0.3
        with LatestFrame(src, lost_timeout_s=0.5) as cam:
            assert wait_for(lambda: server.connected)
            img = np.arange(40 * 64 * 3, dtype=np.uint8).reshape(40, 64, 3)
            assert server.send(img, 1.25)
            frame = cam.get(timeout_s=2.0)
            assert frame.t_s == 1.25 and np.array_equal(frame.image, img)
            server.disconnect()  # the camera unplugged: lost, not end of stream
            with pytest.raises(CameraLost):
                cam.get(timeout_s=2.0)
    finally:
        server.close()


def test_a_malformed_header_is_a_lost_camera():
    server = FrameStreamServer()
    try:
        src = FrameStreamSource(server.url, lost_timeout_s=0.5)
        src.open()
        assert wait_for(lambda: server.connected)
        with server._lock:
            server._client.sendall(b"NOPE" + bytes(20))
        with pytest.raises(CameraLost, match="malformed"):
            src.read()
        src.close()
    finally:
        server.close()
