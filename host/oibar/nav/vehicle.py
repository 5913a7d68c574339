"""The vehicle interface: where guidance's relative-velocity setpoints go (SPEC section 5).

The service vehicle's own GNC is not ours; it takes a velocity and angular-rate setpoint in the
docking frame D (oibar.geometry.docking) at 10 Hz and flies it. Implement :class:`VehicleInterface`
for your vehicle and pass it to the daemon (``oibar nav --vehicle python:mypkg.mod:MyVehicle``).

Shipped sinks:
- :class:`NullVehicle` (``--vehicle none``): keeps the last setpoint, for bench tests with a
  camera and an MCU but no vehicle;
- :class:`UdpJsonVehicle` (``--vehicle udp://HOST:PORT``): one JSON datagram per setpoint,
  ``{"t_s", "v_D_mps": [x, y, z], "w_rad_s": [x, y, z], "phase", "hold"}``, for a GNC computer
  on the network (fire and forget: a lost datagram is replaced 100 ms later). The GNC computer
  may send its odometry back to the address the setpoints come from (see the class);
- the HIL rig's world (oibar_hil.rig), in simulation.

Contract: ``send`` must not block for long (it runs inside the 10 Hz cycle); ``hold`` is called
on shutdown and whenever guidance cannot steer (it must bring the relative velocity to zero).

Optional odometry: ``relative_velocity(t_s)`` returns the vehicle's own measurement of the
relative velocity in D, :class:`RelativeVelocity` ``(t_s, v_D_mps, sigma_mps)`` (time of
validity on the daemon's clock, i.e. the ``t_s`` that ``send`` receives, not after the asked
``t_s``; velocity in m/s; 1-sigma per axis in m/s), or None when it has none (the default;
NullVehicle reports none, UdpJsonVehicle what the GNC computer sends back). Report each
measurement once: the filter treats every one it gets as new information. The daemon asks once per cycle and
the navigation filter fuses it with the camera (oibar.nav.filter ``update_velocity``): the
camera's closing speed has a bias of 10 mm/s and more at contact, the vehicle's IMU/GNC knows it
to a few mm/s, and the MCU records the capture against it (<= 50 mm/s). It must not block
either; an exception from it counts as no measurement.

Optional relative attitude: ``relative_attitude(t_s)`` returns what the vehicle knows of the
relative attitude, :class:`RelativeAttitude` ``(t_s, att_rad, sigma_rad)`` (its own attitude from
its star tracker and gyros against the target's known attitude, as the attitude error in D; its
1-sigma per axis, the target's attitude knowledge included), or None (the default). The
navigator checks the camera's attitude against it every frame (oibar.nav.integrity); the same
rules hold: never block, an exception counts as none.
"""

from __future__ import annotations

import importlib
import json
import socket
from abc import ABC, abstractmethod
from typing import Any, NamedTuple

import numpy as np


class VehicleError(RuntimeError):
    """A vehicle interface could not be created or reached."""


class RelativeVelocity(NamedTuple):
    """The vehicle's own relative-velocity measurement (odometry), docking frame D."""

    t_s: float  # time of validity, daemon clock
    v_D_mps: np.ndarray  # (3,)
    sigma_mps: float  # 1-sigma per axis


class RelativeAttitude(NamedTuple):
    """The vehicle's own relative attitude: the attitude error ``att_rad`` (rotation vector from
    the aligned attitude, body frame, rad: the navigation filter's ``att_rad``) and its 1-sigma
    per axis (rad), valid at ``t_s`` on the daemon's clock."""

    t_s: float
    att_rad: np.ndarray  # (3,)
    sigma_rad: float


class VehicleInterface(ABC):
    @abstractmethod
    def send(self, t_s: float, v_D_mps: np.ndarray, w_rad_s: np.ndarray, phase: str) -> None:
        """A relative-velocity setpoint (D frame) and an attitude-rate setpoint (body)."""

    def relative_velocity(self, t_s: float) -> RelativeVelocity | None:
        """The latest own relative-velocity measurement at or before t_s, or None (no odometry)."""
        return None

    def relative_attitude(self, t_s: float) -> RelativeAttitude | None:
        """The vehicle's own relative attitude at or before t_s, or None (the default): its
        attitude from its own sensors against the target's known attitude, as the attitude error
        in D that the navigation filter keeps (oibar.nav.integrity checks the camera's against
        it). Like ``relative_velocity``: never block, and an exception counts as none."""
        return None

    def hold(self, t_s: float) -> None:
        self.send(t_s, np.zeros(3), np.zeros(3), "HOLD")

    def statistics(self) -> dict[str, Any]:
        """Counters worth keeping in the log's footer (send errors, odometry taken / refused)."""
        return {}

    def close(self) -> None:  # noqa: B027  (a default: only a vehicle with resources overrides it)
        """Release resources; the daemon calls hold() first."""


class NullVehicle(VehicleInterface):
    def __init__(self) -> None:
        self.last: tuple[float, np.ndarray, np.ndarray, str] | None = None

    def send(self, t_s: float, v_D_mps: np.ndarray, w_rad_s: np.ndarray, phase: str) -> None:
        self.last = (t_s, np.asarray(v_D_mps, float).copy(), np.asarray(w_rad_s, float).copy(), phase)


class UdpJsonVehicle(VehicleInterface):
    """Setpoints out as JSON datagrams; the GNC computer's odometry back on the same socket.

    Odometry datagram (optional; send it to the address the setpoints come from):
    ``{"v_D_mps": [x, y, z], "sigma_mps": s, "t_s": t}``: relative velocity in the docking frame
    D (m/s), its 1-sigma per axis (m/s), and its time of validity on the daemon's clock, which the
    GNC computer has from the setpoints: the ``t_s`` of the last setpoint it received plus its own
    time elapsed since then. Without ``t_s`` the measurement counts as valid when the daemon reads
    it (up to one cycle late: give ``t_s`` when you can). The newest measurement is fused once;
    one older than ``max_age_s`` is dropped; a malformed one, or one from the future, is counted
    in ``odometry_rejected`` and ignored, never raised.

    The same datagram (or one of its own) may carry the relative attitude: ``"att_rad": [x, y,
    z]`` (the attitude error in D, a rotation vector, rad) and ``"att_sigma_rad": s``, under the
    same ``t_s`` and the same rules (``attitude_received``, ``attitude_rejected``).
    """

    max_age_s = 0.5  # odometry older than this is stale (5 cycles)
    future_tolerance_s = 0.05  # clock jitter allowed between the GNC's t_s and ours

    def __init__(self, host: str, port: int) -> None:
        self.addr = (host, int(port))
        try:
            self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            self.sock.setblocking(False)
        except OSError as exc:
            raise VehicleError(f"udp://{host}:{port}: {exc}") from exc
        self.errors = 0
        self.odometry_received = 0
        self.odometry_rejected = 0
        self.attitude_received = 0
        self.attitude_rejected = 0
        self._latest: RelativeVelocity | None = None
        self._latest_att: RelativeAttitude | None = None

    def send(self, t_s: float, v_D_mps: np.ndarray, w_rad_s: np.ndarray, phase: str) -> None:
        msg = {
            "t_s": float(t_s),
            "v_D_mps": [float(v) for v in v_D_mps],
            "w_rad_s": [float(v) for v in w_rad_s],
            "phase": phase,
            "hold": phase == "HOLD",
        }
        try:
            self.sock.sendto(json.dumps(msg).encode(), self.addr)
        except OSError:
            self.errors += 1  # the next cycle sends a fresh setpoint

    def relative_velocity(self, t_s: float) -> RelativeVelocity | None:
        """The newest valid measurement not yet reported (never blocks)."""
        self.drain(t_s)
        odo, self._latest = self._latest, None
        if odo is None or t_s - odo.t_s > self.max_age_s:
            return None
        return odo

    def relative_attitude(self, t_s: float) -> RelativeAttitude | None:
        """The newest valid relative attitude not older than ``max_age_s`` (never blocks). Unlike
        odometry it is not used up: the check compares every frame with it."""
        self.drain(t_s)
        att = self._latest_att
        if att is None or t_s - att.t_s > self.max_age_s:
            return None
        return att

    max_datagrams_per_cycle = 256  # bounds the work a flooding sender can put in the 10 Hz cycle

    def drain(self, now_s: float) -> None:
        """Read the datagrams waiting on the socket; keep the newest valid measurements."""
        for _ in range(self.max_datagrams_per_cycle):
            try:
                data, _ = self.sock.recvfrom(2048)
            except OSError:  # nothing waiting (BlockingIOError) or a socket error: next cycle
                break
            try:
                msg = json.loads(data)
                t = float(msg["t_s"]) if msg.get("t_s") is not None else now_s
            except (ValueError, TypeError, KeyError, AttributeError):
                msg, t = None, float("nan")
            if not isinstance(msg, dict) or not np.isfinite(t) or t > now_s + self.future_tolerance_s:
                self.odometry_rejected += 1
                continue
            t = min(t, now_s)
            if "att_rad" in msg or "att_sigma_rad" in msg:
                att = _vector_and_sigma(msg, "att_rad", "att_sigma_rad")
                if att is None:
                    self.attitude_rejected += 1
                else:
                    self.attitude_received += 1
                    if self._latest_att is None or t >= self._latest_att.t_s:
                        self._latest_att = RelativeAttitude(t, *att)
                if "v_D_mps" not in msg and "sigma_mps" not in msg:
                    continue  # an attitude datagram alone
            odo = _vector_and_sigma(msg, "v_D_mps", "sigma_mps")
            if odo is None:
                self.odometry_rejected += 1
                continue
            self.odometry_received += 1
            if self._latest is None or t >= self._latest.t_s:
                self._latest = RelativeVelocity(t, *odo)

    def statistics(self) -> dict[str, Any]:
        return {
            "send_errors": self.errors,
            "odometry_received": self.odometry_received,
            "odometry_rejected": self.odometry_rejected,
            "attitude_received": self.attitude_received,
            "attitude_rejected": self.attitude_rejected,
        }

    def close(self) -> None:
        self.sock.close()


def _vector_and_sigma(msg: dict[str, Any], vec_key: str, sigma_key: str) -> tuple[np.ndarray, float] | None:
    """``msg[vec_key]`` (3 finite numbers) and ``msg[sigma_key]`` (finite, above zero), or None."""
    try:
        v = np.asarray(msg[vec_key], dtype=float)
        sigma = float(msg[sigma_key])
    except (ValueError, TypeError, KeyError):
        return None
    if v.shape != (3,) or not np.all(np.isfinite(v)) or not (np.isfinite(sigma) and sigma > 0):
        return None
    return v, sigma


def open_vehicle(spec: str) -> VehicleInterface:
    """``none`` | ``udp://HOST:PORT`` | ``python:package.module:ClassName`` (no arguments)."""
    if spec in ("", "none", "null"):
        return NullVehicle()
    if spec.startswith("udp://"):
        hostport = spec[len("udp://") :]
        host, sep, port = hostport.rpartition(":")
        if not sep or not port.isdigit():
            raise VehicleError(f"{spec!r}: expected udp://HOST:PORT")
        return UdpJsonVehicle(host or "127.0.0.1", int(port))
    if spec.startswith("python:"):
        target = spec[len("python:") :]
        mod_name, sep, cls_name = target.partition(":")
        if not sep:
            raise VehicleError(f"{spec!r}: expected python:package.module:ClassName")
        try:
            cls = getattr(importlib.import_module(mod_name), cls_name)
        except (ImportError, AttributeError) as exc:
            raise VehicleError(f"{spec!r}: cannot load ({exc})") from exc
        obj = cls()
        if not isinstance(obj, VehicleInterface):
            raise VehicleError(
                f"{spec!r}: {cls_name} does not derive from oibar.nav.vehicle.VehicleInterface"
            )
        return obj
    raise VehicleError(f"unknown vehicle {spec!r}: use none, udp://HOST:PORT or python:module:Class")
