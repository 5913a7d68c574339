"""Where an install finds the shipped model, and the versions it carries (``oibar --version``).

A wheel or an sdist carries the shipped models as package data in ``oibar/models/`` (copied from
the checkout's ``models/`` at build time, host/setup.py); a checkout (an editable install, or
``PYTHONPATH=host``) reads them from ``models/`` at the repository root. The default model's side
files (its first pass and its far network, named in its ONNX metadata) lie beside it in both.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

from oibar import __version__

DEFAULT_MODEL = "oibarnet.onnx"
"""The shipped model: the default of ``oibar nav`` and ``oibar replay`` (docs/model_card.md)."""

PACKAGE_MODELS = Path(__file__).resolve().parent / "models"
"""The shipped models inside an installed wheel (absent in a checkout)."""


def checkout_models() -> Path | None:
    """``models/`` of the OIBAR checkout this package runs from, if it runs from one."""
    for parent in Path(__file__).resolve().parents:
        if (parent / "models" / DEFAULT_MODEL).is_file() and (parent / "proto" / "oibar.proto").is_file():
            return parent / "models"
    return None


def default_model_path() -> Path:
    """$OIBAR_MODEL, else the installed package's model, else the checkout's, else the relative
    ``models/oibarnet.onnx`` (whose absence the model loader then reports)."""
    env = os.environ.get("OIBAR_MODEL")
    if env:
        return Path(env)
    if (PACKAGE_MODELS / DEFAULT_MODEL).is_file():
        return PACKAGE_MODELS / DEFAULT_MODEL
    found = checkout_models()
    if found is not None:
        return found / DEFAULT_MODEL
    return Path("models") / DEFAULT_MODEL


def model_metadata(path: Path) -> dict[str, Any]:
    """The ``oibar.*`` metadata of an ONNX export, JSON-decoded (no weights are read into a
    session; a value that is not JSON is kept as text)."""
    import onnx

    meta: dict[str, Any] = {}
    for prop in onnx.load(str(path), load_external_data=False).metadata_props:
        if prop.key.startswith("oibar."):
            try:
                meta[prop.key[6:]] = json.loads(prop.value)
            except ValueError:
                meta[prop.key[6:]] = prop.value
    return meta


def model_version_text(path: Path) -> str:
    """``0.35.15 (finetune_finetune; finder 0.1.0, first pass 0.3.0) PATH``: the export and each
    file beside it that it names (far network, finder, first pass), or what is wrong with the
    file: this line must never fail."""
    from oibar.nav.pose.model_file import COMPANION_ROLES, companion_files

    try:
        meta = model_metadata(path)
        files = companion_files(meta)
        parts = [
            f"{COMPANION_ROLES[role]} {model_metadata(path.parent / files[role]).get('model_version', '?')}"
            for role in ("far_network", "finder", "first_pass")
            if role in files
        ]
        name = str(meta.get("name", "?"))
        inside = f"{name}; {', '.join(parts)}" if parts else name
        return f"{meta.get('model_version', '?')} ({inside}) {path}"
    except Exception as exc:  # a missing or broken file: say so, and still print the rest
        return f"unreadable: {path} ({type(exc).__name__}: {exc})"


def version_text(model: Path | None = None) -> str:
    """The package, link protocol and model versions, one per line."""
    from oibar import pb

    model = model or default_model_path()
    return "\n".join(
        (
            f"oibar {__version__}",
            f"protocol {pb.PROTOCOL_VERSION}",
            f"model {model_version_text(model)}",
        )
    )
