"""Low-precision Sun (Astronomical Almanac formulae, as in Vallado's algorithm for the Sun).

Accurate to about 0.01 deg over 1950-2050, which is far below anything visible at our image
scale. Output frame: mean equator and equinox of date; we use it as TEME (the difference,
equinox precession of date vs TEME's mean equinox, is a few arcseconds)."""

from __future__ import annotations

import numpy as np

AU_KM = 149_597_870.7
JD_J2000 = 2451545.0


def sun_position_au(jd: float) -> np.ndarray:
    """Geocentric Sun position vector, AU, equatorial frame of date, at Julian date `jd` (UT)."""
    t_cent = (jd - JD_J2000) / 36525.0
    mean_lon_deg = 280.460 + 36000.771 * t_cent
    mean_anom = np.radians(357.5291092 + 35999.05034 * t_cent)
    ecl_lon = np.radians(mean_lon_deg + 1.914666471 * np.sin(mean_anom) + 0.019994643 * np.sin(2 * mean_anom))
    dist_au = 1.000140612 - 0.016708617 * np.cos(mean_anom) - 0.000139589 * np.cos(2 * mean_anom)
    obliquity = np.radians(23.439291 - 0.0130042 * t_cent)
    return dist_au * np.array(
        [
            np.cos(ecl_lon),
            np.cos(obliquity) * np.sin(ecl_lon),
            np.sin(obliquity) * np.sin(ecl_lon),
        ]
    )


def sun_direction(jd: float) -> np.ndarray:
    """Unit vector from Earth's centre towards the Sun (equatorial frame of date)."""
    r = sun_position_au(jd)
    return r / np.linalg.norm(r)


def ecliptic_longitude_deg(jd: float) -> float:
    """Geometric ecliptic longitude of the Sun, degrees in [0, 360)."""
    t_cent = (jd - JD_J2000) / 36525.0
    m = np.radians(357.5291092 + 35999.05034 * t_cent)
    lon = 280.460 + 36000.771 * t_cent + 1.914666471 * np.sin(m) + 0.019994643 * np.sin(2 * m)
    return float(lon % 360.0)


def right_ascension_declination_deg(jd: float) -> tuple[float, float]:
    x, y, z = sun_direction(jd)
    return float(np.degrees(np.arctan2(y, x)) % 360.0), float(np.degrees(np.arcsin(z)))
