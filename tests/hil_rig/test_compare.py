"""``python -m oibar_hil.rig.compare``: two flights' navigation side by side, from the rig report's
nav_cycles.csv (written here by the report's own writer)."""

import numpy as np
import pytest

from oibar_hil.rig.compare import band_table, load, main
from oibar_hil.rig.report import write_nav_cycles


def flight(path, off_axis_m, lateral_err_m, replaced=False):
    """A straight approach from 10 m to 0.6 m, the chaser ``off_axis_m(range)`` off the axis."""
    rows = []
    for r in np.linspace(10.0, 0.6, 95):
        rows.append(
            {
                "t_s": 10.0 - r,
                "range_true_m": r,
                "true_x_m": 0.6 * off_axis_m(r),
                "true_y_m": 0.8 * off_axis_m(r),
                "lateral_err_m": lateral_err_m(r),
                "ans_err_att_x_deg": 3.0,
                "ans_err_att_y_deg": 4.0,
                **({"att_check_deg": 15.0, "att_replaced": r > 5.0} if replaced else {}),
            }
        )
    write_nav_cycles(rows, path)
    return path


def test_the_band_table_finds_the_excursion_where_it_was(tmp_path):
    before = flight(tmp_path / "before.csv", lambda r: 1.9 if 4.0 <= r < 6.0 else 0.1, lambda r: 0.05 * r)
    c = load(before)
    assert c["off_axis_true_m"] == pytest.approx(
        np.where((c["range_true_m"] >= 4) & (c["range_true_m"] < 6), 1.9, 0.1)
    )
    assert c["att_err_deg"] == pytest.approx(5.0)
    bands = {(b["from_m"], b["to_m"]): b for b in band_table(c)}
    assert bands[(4.0, 6.0)]["off_axis_true_m_max"] == pytest.approx(1.9)
    assert bands[(6.0, 8.0)]["off_axis_true_m_max"] == pytest.approx(0.1)
    assert bands[(0.5, 2.0)]["lateral_err_m_p95"] < 0.1 < bands[(8.0, 11.0)]["lateral_err_m_p95"]
    assert sum(b["cycles"] for b in bands.values()) == 95


def test_the_comparison_draws_both_flights_and_says_what_it_cannot_read(tmp_path, capsys):
    before = flight(tmp_path / "before.csv", lambda r: 1.9 if 4.0 <= r < 6.0 else 0.1, lambda r: 0.3)
    after = flight(tmp_path / "after.csv", lambda r: 0.1, lambda r: 0.05, replaced=True)
    out = tmp_path / "compare.png"
    assert main([str(before), str(after), "--labels", "before", "after", "--out", str(out)]) == 0
    assert out.stat().st_size > 10_000
    text = capsys.readouterr().out
    assert "off the axis (true) max 1.90 m" in text and "off the axis (true) max 0.10 m" in text
    wrong = tmp_path / "wrong.csv"
    wrong.write_text("t_s,foo\n1,2\n")
    assert main([str(wrong), "--out", str(out)]) == 2
    assert "no column 'range_true_m'" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main([str(before), str(after), "--labels", "one"])
