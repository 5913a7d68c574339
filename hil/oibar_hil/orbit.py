"""Target orbit: SGP4 propagation of a TLE, LVLH frame, Sun and Earth as seen from the target.

The default TLE is an ISS-like orbit written for this project (not a real element set): 51.64 deg
inclination, ~420 km altitude, right ascension of the node 0 deg at the March 2024 equinox so
that the Sun lies close to the orbit plane (beta angle near 0) on the default date.
SGP4 includes J2 and drag (via B*), like the paper's simulator.
"""

from __future__ import annotations

from dataclasses import dataclass
from datetime import UTC, datetime, timedelta

import numpy as np
from sgp4.api import Satrec, jday

from .frames import lvlh_rotation
from .sun import sun_direction

EARTH_RADIUS_KM = 6378.137


def tle_checksum(line: str) -> int:
    return sum(int(c) if c.isdigit() else (1 if c == "-" else 0) for c in line[:68]) % 10


def _with_checksum(line68: str) -> str:
    assert len(line68) == 68, len(line68)
    return line68 + str(tle_checksum(line68))


DEFAULT_TLE = (
    _with_checksum("1 99001U 24001A   24080.00000000  .00016000  00000-0  28000-3 0  999"),
    _with_checksum("2 99001  51.6400   0.0000 0005000  90.0000 270.0000 15.50000000 1000"),
)
DEFAULT_EPOCH_UTC = "2024-03-20T00:00:00+00:00"


def parse_utc(text: str) -> datetime:
    dt = datetime.fromisoformat(text.replace("Z", "+00:00"))
    return dt if dt.tzinfo else dt.replace(tzinfo=UTC)


def julian_date(when: datetime) -> float:
    w = when.astimezone(UTC)
    jd, fr = jday(w.year, w.month, w.day, w.hour, w.minute, w.second + w.microsecond * 1e-6)
    return jd + fr


def gmst_rad(jd_ut1: float) -> float:
    """Greenwich mean sidereal time (IAU-82), radians."""
    t = (jd_ut1 - 2451545.0) / 36525.0
    sec = 67310.54841 + (876600.0 * 3600.0 + 8640184.812866) * t + 0.093104 * t * t - 6.2e-6 * t**3
    return float(np.radians((sec % 86400.0) / 240.0))


@dataclass(frozen=True)
class TargetState:
    jd: float
    r_teme_km: np.ndarray
    v_teme_kmps: np.ndarray
    R_teme_lvlh: np.ndarray
    sun_lvlh: np.ndarray  # unit vector target -> Sun, LVLH
    R_ecef_lvlh: np.ndarray  # rotates LVLH vectors into Earth-fixed (for Earth texture)

    @property
    def altitude_km(self) -> float:
        return float(np.linalg.norm(self.r_teme_km) - EARTH_RADIUS_KM)

    @property
    def earth_center_lvlh_km(self) -> np.ndarray:
        return np.array([0.0, 0.0, float(np.linalg.norm(self.r_teme_km))])

    @property
    def beta_deg(self) -> float:
        """Sun angle above the orbit plane (positive towards the orbit normal, i.e. -Y LVLH)."""
        return float(np.degrees(np.arcsin(-self.sun_lvlh[1])))


def sun_inplane_elevation_deg(sun_lvlh: np.ndarray) -> float:
    """Sun angle in the orbit plane, measured from +V-bar towards the zenith (-R-bar), in
    [0, 360): 0 = ahead on the horizon, 90 = overhead, 180 = behind on the horizon. Values in
    (0, 180) mean the Sun is above the local horizontal plane. This is our reading of the
    paper's "Sun elevation" column (values up to 165 deg)."""
    return float(np.degrees(np.arctan2(-sun_lvlh[2], sun_lvlh[0])) % 360.0)


class TargetOrbit:
    def __init__(self, tle: tuple[str, str] = DEFAULT_TLE):
        self.tle = tle
        self._sat = Satrec.twoline2rv(tle[0], tle[1])

    @property
    def period_s(self) -> float:
        return 2 * np.pi / self._sat.no_kozai * 60.0

    def state(self, jd: float) -> TargetState:
        err, r, v = self._sat.sgp4(float(np.floor(jd)), float(jd - np.floor(jd)))
        if err != 0:
            raise RuntimeError(f"SGP4 error code {err} at JD {jd}")
        r, v = np.array(r), np.array(v)
        R_teme_lvlh = lvlh_rotation(r, v)
        sun_lvlh = R_teme_lvlh.T @ sun_direction(jd)
        g = gmst_rad(jd)
        R_ecef_teme = np.array([[np.cos(g), np.sin(g), 0.0], [-np.sin(g), np.cos(g), 0.0], [0.0, 0.0, 1.0]])
        return TargetState(jd, r, v, R_teme_lvlh, sun_lvlh, R_ecef_teme @ R_teme_lvlh)

    def time_for_sun_elevation(self, start: datetime, elevation_deg: float) -> datetime:
        """First time within one orbit after `start` at which the in-plane Sun elevation
        equals `elevation_deg` (coarse scan, then bisection to ~1 ms)."""
        jd0 = julian_date(start)

        def err(t_s: float) -> float:
            e = sun_inplane_elevation_deg(self.state(jd0 + t_s / 86400.0).sun_lvlh) - elevation_deg
            return (e + 180.0) % 360.0 - 180.0

        step_s = 20.0
        t, e = 0.0, err(0.0)
        while t < self.period_s + step_s:
            t2 = t + step_s
            e2 = err(t2)
            if abs(e) < 1e-9:
                return start + timedelta(seconds=t)
            # A real crossing, not the +-180 wrap.
            if np.sign(e) != np.sign(e2) and abs(e - e2) < 90.0:
                lo, hi = t, t2
                for _ in range(40):
                    mid = 0.5 * (lo + hi)
                    if np.sign(err(mid)) == np.sign(e):
                        lo = mid
                    else:
                        hi = mid
                return start + timedelta(seconds=round(0.5 * (lo + hi), 3))
            t, e = t2, e2
        raise ValueError(f"Sun never reaches in-plane elevation {elevation_deg} deg in one orbit")
