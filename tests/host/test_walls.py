"""The walls between the project's parts (docs/architecture.md), read from the source.

Every module's imports are read with ast, function-local ones included (a lazy import crosses a
wall as surely as a top-level one), and checked against the rules below. A broken wall fails
with the module, the import and the rule, e.g.
    host/oibar/nav/filter.py:12 imports oibar_models.metrics: flight code imports neither the
    simulator nor the training library nor torch (rule 'flight')
"""

from __future__ import annotations

import ast
from dataclasses import dataclass
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
PACKAGES = {
    "oibar": ROOT / "host" / "oibar",
    "oibar_hil": ROOT / "hil" / "oibar_hil",
    "oibar_models": ROOT / "models" / "oibar_models",
    "oibar_bench": ROOT / "bench" / "oibar_bench",
}

SIMULATOR_AND_TRAINING = (
    "oibar_hil",
    "oibar_models",
    "oibar_bench",
    "torch",
    "torchvision",
    "trimesh",
    "manifold3d",
    "moderngl",
    "matplotlib",
)


@dataclass(frozen=True)
class Rule:
    name: str
    modules: tuple[str, ...]  # the rule applies to these modules and everything under them
    forbidden: tuple[str, ...]  # top-level names or dotted prefixes they may not import
    why: str
    allowed: tuple[str, ...] = ()  # dotted prefixes allowed although a forbidden prefix matches


RULES = (
    Rule(
        "flight",
        (
            "oibar.nav",
            "oibar.link",
            "oibar.camera",
            "oibar.geometry",
            "oibar.cli",
            "oibar.pb",
            "oibar.config",  # the daemon's configuration file, read before it flies
            "oibar.sdnotify",  # its systemd readiness and watchdog
        ),
        SIMULATOR_AND_TRAINING + ("oibar.calib",),
        "flight code imports neither the simulator nor the training library nor torch, nor the lab toolbox",
        allowed=("oibar.calib.cli",),
    ),  # `oibar calib ...` is registered lazily by the CLI
    Rule(
        "geometry",
        ("oibar.geometry",),
        ("oibar.nav", "oibar.link", "oibar.camera", "oibar.calib", "cv2", "scipy", "PIL", "onnxruntime"),
        "oibar.geometry is numpy only: everything else builds on it",
    ),
    Rule(
        "calib",
        ("oibar.calib",),
        SIMULATOR_AND_TRAINING,
        "the lab toolbox imports no simulator and no training library (its synthetic validation is "
        "oibar_hil.calib_synth)",
    ),
    Rule(
        "host",
        ("oibar",),
        ("oibar_hil", "oibar_models", "oibar_bench"),
        "the host package (pip install ./host) stands alone: studies live in models/ or bench/",
    ),
    Rule(
        "hil",
        ("oibar_hil",),
        ("oibar_models", "oibar_bench", "torch"),
        "the simulator does not depend on the training library",
    ),
)


@dataclass(frozen=True)
class Import:
    module: str  # the importing module, dotted
    path: Path
    line: int
    target: str  # the imported module, dotted and absolute


def module_name(pkg: str, root: Path, path: Path) -> str:
    parts = list(path.relative_to(root).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join([pkg] + parts)


def imports_of(path: Path, module: str) -> list[Import]:
    tree = ast.parse(path.read_text(), filename=str(path))
    is_pkg = path.name == "__init__.py"
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out += [Import(module, path, node.lineno, a.name) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = module.split(".")
                base = base[: len(base) - node.level + (1 if is_pkg else 0)]
                prefix = ".".join(base + ([node.module] if node.module else []))
            else:
                prefix = node.module or ""
            # `from pkg import name` may import the submodule pkg.name: check both
            out += [Import(module, path, node.lineno, prefix)]
            out += [
                Import(module, path, node.lineno, f"{prefix}.{a.name}") for a in node.names if a.name != "*"
            ]
    return out


def all_imports() -> list[Import]:
    out = []
    for pkg, root in PACKAGES.items():
        for path in sorted(root.rglob("*.py")):
            out += imports_of(path, module_name(pkg, root, path))
    return out


def _under(name: str, prefix: str) -> bool:
    return name == prefix or name.startswith(prefix + ".")


def violations(imports: list[Import], root: Path = ROOT) -> list[str]:
    """One message per broken wall: where, which module, what it imports, which rule and why."""
    found: dict[tuple, str] = {}
    for imp in sorted(imports, key=lambda i: len(i.target)):  # `from a import b`: report a, not a.b too
        for rule in RULES:
            if not any(_under(imp.module, m) for m in rule.modules):
                continue
            bad = [f for f in rule.forbidden if _under(imp.target, f)]
            if bad and not any(_under(imp.target, a) for a in rule.allowed):
                found.setdefault(
                    (imp.path, imp.line, rule.name),
                    f"{imp.path.relative_to(root)}:{imp.line} ({imp.module}) imports {imp.target}: "
                    f"{rule.why} (rule '{rule.name}')",
                )
    return sorted(found.values())


def test_the_walls_hold():
    imports = all_imports()
    assert len({i.module for i in imports}) > 100  # the walk did find the packages
    problems = violations(imports)
    assert not problems, "broken walls:\n  " + "\n  ".join(problems)


def test_function_local_and_relative_imports_are_seen(tmp_path):
    """The checker itself: a lazy import inside a function and a relative import are both caught,
    with the module, the import and the rule in the message."""
    pkg = tmp_path / "oibar" / "nav"
    pkg.mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "study.py").write_text(
        "import numpy\n\n\ndef f():\n    from oibar_models import metrics\n    return metrics\n"
    )
    (pkg / "lab.py").write_text("from ..calib import pnp\n")
    imports = []
    for p in sorted(pkg.glob("*.py")):
        imports += imports_of(p, module_name("oibar", tmp_path / "oibar", p))
    msgs = violations(imports, root=tmp_path)
    assert any(
        "study.py:5 (oibar.nav.study) imports oibar_models" in m and "rule 'flight'" in m for m in msgs
    ), msgs
    assert any("oibar.nav.lab" in m and "imports oibar.calib" in m and "rule 'flight'" in m for m in msgs), (
        msgs
    )
    assert not any("numpy" in m for m in msgs)


@pytest.mark.parametrize("module", ["oibar.geometry.camera", "oibar.nav.daemon", "oibar.calib.pipeline"])
def test_a_forbidden_import_would_fail(module):
    """Planting a forbidden import in a real module's import list makes the wall check fail."""
    imports = all_imports()
    planted = next(i for i in imports if i.module == module)
    bad = Import(module, planted.path, 1, "oibar_hil.meshes")
    problems = violations(imports + [bad])
    assert problems and all("oibar_hil.meshes" in p for p in problems)


@pytest.mark.parametrize("module", ["oibar.config", "oibar.sdnotify"])
def test_config_and_watchdog_are_flight_code(module):
    """The configuration file the daemon reads before it flies and its systemd watchdog are
    flight code: torch or the lab toolbox planted in them breaks the flight wall."""
    imports = all_imports()
    planted = next(i for i in imports if i.module == module)
    for target in ("torch", "oibar.calib.pipeline"):
        problems = violations(imports + [Import(module, planted.path, 1, target)])
        assert any(target in p and "rule 'flight'" in p for p in problems), problems
