"""oibar.machine: the CPU a measurement or a build names (bench tables, build stage records)."""

from __future__ import annotations

import platform
from pathlib import Path

import pytest

from oibar.machine import cpu_model


def test_the_cpu_model_is_cpuinfos_model_name(monkeypatch):
    text = "processor\t: 0\nvendor_id\t: X\nmodel name\t: Some CPU @ 2.0GHz\nmodel name\t: Other\n"
    monkeypatch.setattr(Path, "read_text", lambda self, *a, **k: text)
    assert cpu_model() == "Some CPU @ 2.0GHz"


def test_without_cpuinfo_the_cpu_model_is_what_platform_says(monkeypatch):
    def unreadable(self, *a, **k):
        raise OSError("no /proc here")

    monkeypatch.setattr(Path, "read_text", unreadable)
    monkeypatch.setattr(platform, "processor", lambda: "")
    monkeypatch.setattr(platform, "machine", lambda: "riscv64")
    assert cpu_model() == "riscv64"
    monkeypatch.setattr(Path, "read_text", lambda self, *a, **k: "processor\t: 0\n")  # no model name
    assert cpu_model() == "riscv64"


@pytest.mark.skipif(not Path("/proc/cpuinfo").is_file(), reason="Linux only")
def test_on_this_machine_it_names_a_cpu():
    assert cpu_model() and cpu_model() != "unknown"
