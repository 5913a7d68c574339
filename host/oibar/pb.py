"""The generated protobuf module for ``proto/oibar.proto``, under a stable name.

``oibar/_generated/oibar_pb2.py`` is produced at build time by protoc and is not in git (host/setup.py
writes it into every wheel and sdist, and into the checkout on an editable install; ``make gen``
too), so every other module imports the schema from here: if the file is missing the user gets
one clear instruction instead of a bare ``ModuleNotFoundError``.
"""

from __future__ import annotations

from typing import Any

try:
    from oibar._generated import oibar_pb2
except ModuleNotFoundError as exc:  # only a missing file earns the "make gen" hint
    if exc.name not in ("oibar._generated", "oibar._generated.oibar_pb2"):
        raise
    raise ImportError(
        "the generated protobuf module oibar/_generated/oibar_pb2.py is missing: "
        "run `make gen` at the repository root, or reinstall the package (pip install ./host)"
    ) from exc

from oibar._generated.oibar_pb2 import *  # noqa: E402,F401,F403  (re-export the schema)

# (the star import brought PROTOCOL_VERSION as the enum member; this is the same number, as int)
PROTOCOL_VERSION: int = oibar_pb2.Protocol.Value("PROTOCOL_VERSION")  # type: ignore[no-redef]
"""This build's link protocol version (from the schema, never a local copy)."""

MAX_PACKET_BYTES: int = oibar_pb2.Protocol.Value("PROTOCOL_MAX_PACKET_BYTES")
"""Largest encoded ``Packet`` before framing."""

MAX_FRAME_BYTES: int = oibar_pb2.Protocol.Value("PROTOCOL_MAX_FRAME_BYTES")
"""Largest wire frame, 0x00 delimiter included."""


def enum_name(enum_type: Any, value: int) -> str:
    """Name of ``value`` in ``enum_type``, or ``"<EnumName>(<value>)"`` if unknown.

    proto3 enums are open: a newer peer may send a value this build does not know, and a
    log line or a result must never fail because of that.
    """
    try:
        return str(enum_type.Name(value))
    except ValueError:
        return f"{enum_type.DESCRIPTOR.name}({value})"
