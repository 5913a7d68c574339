"""The FMEA (firmware/fmea.toml, issue 59 item 1) is the source of truth: every row names tests
that exist, every test of the covered suites (the table's `covered_suites`: the hazard, safety,
fault and parameter-store suites) names a row, and docs/fmea.md is the generated page."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from scripts import fmea  # noqa: E402


@pytest.fixture(scope="module")
def table() -> dict:
    return fmea.load()


def test_table_has_no_problem(table: dict) -> None:
    assert fmea.problems(table) == []


def test_covered_suites_include_the_hazard_and_safety_suites(table: dict) -> None:
    must = {
        "tests/firmware/test_app_hazards.c",
        "tests/firmware/test_app_safety.c",
        "tests/firmware/test_app_faults.c",
        "tests/firmware/test_param_store.c",
    }
    assert must <= set(table["covered_suites"])


def test_every_part_of_the_issue_has_rows(table: dict) -> None:
    text = " ".join(r["part"] for r in table["row"]).lower()
    for part in (
        "pressure",
        "position sensor",
        "switch",
        "valve",
        "link",
        "clock",
        "flash",
        "watchdog",
        "stepper",
    ):
        assert part in text, part


def test_committed_doc_is_the_generated_one(table: dict) -> None:
    assert fmea.DOC.read_text(encoding="utf-8") == fmea.markdown(table), "run `make fmea`"


def test_checker_finds_each_kind_of_problem(tmp_path: Path, table: dict) -> None:
    # The check must be able to fail: a row without tests, a test that does not exist, an
    # unknown fault code, and a covered test that no row names.
    (tmp_path / "proto").mkdir()
    (tmp_path / "proto" / "oibar.proto").write_text("enum F {\n  FAULT_NONE = 0;\n  FAULT_A = 1;\n}\n")
    (tmp_path / "t.c").write_text("static void test_one(void) {}\nvoid test_two(void) {}\n")
    (tmp_path / "t.py").write_text("def test_py():\n    pass\n")
    row = {k: "x" for k in fmea.FIELDS} | {"states": ["all"], "fault": "FAULT_A"}
    bad = {
        "covered_suites": ["t.c"],
        "row": [
            row | {"id": "R1", "tests": []},
            row | {"id": "R2", "tests": ["t.c::test_one", "t.c::test_three", "t.py::test_py"]},
            row | {"id": "R3", "fault": "FAULT_B", "tests": ["t.py::test_py"]},
        ],
    }
    found = "\n".join(fmea.problems(bad, tmp_path))
    assert "R1: no tests" in found
    assert "t.c::test_three: no such test" in found
    assert "FAULT_B" in found
    assert "t.c::test_two names no FMEA row" in found
    assert "test_one names no" not in found
