"""Build steps of the ``oibar`` package that pyproject.toml cannot declare (issue 60).

Everything else (name, dependencies, entry point) is in pyproject.toml; setuptools calls this file
for the commands below.

- ``build_py``: the protobuf module ``oibar/_generated/oibar_pb2.py`` (and its ``.pyi`` stub) is
  compiled from ``../proto/oibar.proto`` of the checkout, and the shipped models are copied from
  ``../models/`` into ``oibar/models/`` as package data. An editable install (``pip install -e``)
  writes the protobuf module into the source tree instead (as ``make gen`` does) and ships no
  model copies: ``oibar.resources`` finds the checkout's ``models/``.
- ``sdist``: the release tree gets the same generated files and model copies, so a wheel built
  from the sdist (where ``../proto`` and ``../models`` do not exist) carries them too.

The compiler is ``grpcio-tools``' bundled protoc (a build requirement, pinned to the protoc whose
Python output matches the pinned protobuf runtime); without it, ``protoc`` on PATH.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

from setuptools import setup
from setuptools.command.build_py import build_py as _build_py
from setuptools.command.sdist import sdist as _sdist

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
PROTO = REPO / "proto" / "oibar.proto"
MODELS = REPO / "models"
# The default model of `oibar nav` first (oibar.resources.DEFAULT_MODEL), then the files its ONNX
# metadata names, which must lie beside it: its first pass (oibar.first_pass), its fixture finder
# (oibar.finder) and any far network (oibar.far_network). tests/host/test_packaging.py checks this
# list against that metadata.
SHIPPED_MODELS = ("oibarnet.onnx", "oibarnet_finder.onnx", "oibarnet_lite.onnx")
GENERATED = ("oibar_pb2.py", "oibar_pb2.pyi")


def _from_sdist() -> bool:
    """True when building from an unpacked sdist: it carries the generated files and the models,
    and any ../proto beside it is not ours."""
    return (HERE / "PKG-INFO").is_file() and (HERE / "oibar" / "_generated" / GENERATED[0]).is_file()


def protoc(args: list[str]) -> tuple[int, str, str]:
    """Run the protobuf compiler on ``args``: (exit status, which compiler, its error output).
    SystemExit when there is none."""
    try:
        # The compiler extension itself: the grpc_tools.protoc wrapper imports pkg_resources,
        # which newer setuptools no longer ship.
        import grpc_tools
        from grpc_tools import _protoc_compiler
    except ImportError:
        exe = shutil.which("protoc")
        if exe is None:
            raise SystemExit(
                "oibar build: no protobuf compiler: install grpcio-tools (a build requirement in "
                "host/pyproject.toml) or protoc"
            ) from None
        proc = subprocess.run([exe, *args], capture_output=True, text=True)
        return proc.returncode, exe, proc.stderr.strip()
    include = Path(grpc_tools.__file__).parent / "_proto"  # the well-known types
    rc = _protoc_compiler.run_main([a.encode() for a in ["protoc", f"-I{include}", *args]])
    return rc, f"grpcio-tools {_version('grpcio-tools')}", "(see above)"


def run_protoc(proto: Path, out_dir: Path) -> str:
    """Compile ``proto`` into ``out_dir`` (``*_pb2.py`` and ``*_pb2.pyi``, and an
    ``__init__.py``); returns the compiler used."""
    out_dir.mkdir(parents=True, exist_ok=True)
    rc, used, err = protoc(
        [f"-I{proto.parent}", f"--python_out={out_dir}", f"--pyi_out={out_dir}", str(proto)]
    )
    if rc != 0:
        raise SystemExit(f"oibar build: protoc failed on {proto} ({used}): {err}")
    (out_dir / "__init__.py").touch()
    return used


def _version(dist: str) -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version(dist)
    except PackageNotFoundError:
        return "?"


def write_generated(dest_pkg: Path) -> list[Path]:
    """``dest_pkg/_generated/`` from ../proto; the files written."""
    if not PROTO.is_file():
        raise SystemExit(
            f"oibar build: {PROTO} not found: build from the OIBAR checkout (pip install ./host) "
            "or from an sdist"
        )
    out = dest_pkg / "_generated"
    used = run_protoc(PROTO, out)
    print(f"oibar build: generated {out / GENERATED[0]} from {PROTO.name} with {used}", file=sys.stderr)
    return [out / "__init__.py", *(out / g for g in GENERATED)]


def copy_models(dest_pkg: Path) -> list[Path]:
    """The shipped models into ``dest_pkg/models/``; the files written."""
    missing = [m for m in SHIPPED_MODELS if not (MODELS / m).is_file()]
    if missing:
        raise SystemExit(f"oibar build: shipped model(s) missing in {MODELS}: {', '.join(missing)}")
    out = dest_pkg / "models"
    out.mkdir(parents=True, exist_ok=True)
    written = []
    for name in SHIPPED_MODELS:
        shutil.copyfile(MODELS / name, out / name)
        written.append(out / name)
    return written


class build_py(_build_py):
    def run(self) -> None:
        super().run()
        if _from_sdist():
            return  # the sdist's files were copied as package data
        if getattr(self, "editable_mode", False):
            write_generated(HERE / "oibar")  # imported from the source tree
            return
        self._extra = write_generated(Path(self.build_lib) / "oibar")
        self._extra += copy_models(Path(self.build_lib) / "oibar")

    def get_outputs(self, include_bytecode: bool = True) -> list[str]:
        outs = list(super().get_outputs(include_bytecode))
        return outs + [str(p) for p in getattr(self, "_extra", []) if str(p) not in outs]


class sdist(_sdist):
    def make_release_tree(self, base_dir: str, files: list[str]) -> None:
        super().make_release_tree(base_dir, files)
        if _from_sdist():
            return  # an sdist of an sdist: the files are already in `files`
        pkg = Path(base_dir) / "oibar"
        # hard links from make_release_tree would write through to the checkout: fresh files
        gen = pkg / "_generated"
        if gen.exists():
            shutil.rmtree(gen)
        write_generated(pkg)
        copy_models(pkg)


if __name__ == "__main__":  # setuptools runs this file as __main__; tests import it for the lists
    setup(cmdclass={"build_py": build_py, "sdist": sdist})
