import numpy as np

from oibar_hil.orbit import (
    DEFAULT_EPOCH_UTC,
    DEFAULT_TLE,
    TargetOrbit,
    julian_date,
    parse_utc,
    sun_inplane_elevation_deg,
    tle_checksum,
)
from oibar_hil.sun import right_ascension_declination_deg, sun_position_au


def test_sun_against_meeus_example_25a():
    # Meeus, Astronomical Algorithms (2nd ed.), example 25.a: 1992 Oct 13.0 TD (JDE 2448908.5):
    # apparent RA 198.38083 deg, Dec -7.78507 deg, R = 0.99766 AU.
    ra, dec = right_ascension_declination_deg(2448908.5)
    assert abs(ra - 198.38083) < 0.01
    assert abs(dec - -7.78507) < 0.01
    assert abs(np.linalg.norm(sun_position_au(2448908.5)) - 0.99766) < 1e-4


def test_sun_declination_at_june_solstice():
    jd = julian_date(parse_utc("2024-06-20T20:51:00Z"))  # 2024 June solstice
    _, dec = right_ascension_declination_deg(jd)
    assert abs(dec - 23.44) < 0.01


def test_default_tle_is_valid_and_iss_like():
    for line in DEFAULT_TLE:
        assert int(line[68]) == tle_checksum(line)
    orbit = TargetOrbit()
    st = orbit.state(julian_date(parse_utc(DEFAULT_EPOCH_UTC)))
    assert 380 < st.altitude_km < 450
    assert 90 < orbit.period_s / 60 < 95
    v_lvlh = st.R_teme_lvlh.T @ st.v_teme_kmps
    assert v_lvlh[0] > 7.5 and abs(v_lvlh[1]) < 1e-9  # flies along +V-bar
    assert abs(st.beta_deg) < 2.0  # Sun near the orbit plane by design


def test_time_for_sun_elevation_hits_requested_angle():
    orbit = TargetOrbit()
    start = parse_utc(DEFAULT_EPOCH_UTC)
    for elev in (37, 75, 146, 165):
        t = orbit.time_for_sun_elevation(start, elev)
        st = orbit.state(julian_date(t))
        assert abs(sun_inplane_elevation_deg(st.sun_lvlh) - elev) < 0.01
        assert st.sun_lvlh[2] < 0  # above the local horizon (daylight)
