"""The flight log's own protobuf messages (package ``oibar.log``) and a decoder for any protobuf
channel of an MCAP file.

The messages are declared here, in code, as a ``FileDescriptorProto``: the build compiles only
``proto/oibar.proto`` (the MCU link's schema, which nanopb compiles for the firmware too), and the
flight log must not grow the link's schema. Every MCAP file carries the ``FileDescriptorSet`` of
each channel's schema, so Foxglove, ``mcap`` and ``oibar replay`` decode these messages from the
file alone, without this module.

Numbers are ``double`` (float64), the navigator's own precision: a logged estimate compared with
a replayed one is compared bit for bit. Vectors are ``repeated double`` named with their unit and
frame (``T_cam_target_m``: 3 values; ``q_cam_target_wxyz``: 4); an empty vector means "none".
"""

from __future__ import annotations

from typing import Any

from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

PACKAGE = "oibar.log"
FILE_NAME = "oibar/log.proto"
# A change that an old reader would misread bumps this (RunInfo.log_format_version); adding a
# field does not.
LOG_FORMAT_VERSION = 1

_F = descriptor_pb2.FieldDescriptorProto
DOUBLE, FLOAT, UINT64, UINT32, INT64, BOOL, STRING, BYTES = (
    _F.TYPE_DOUBLE,
    _F.TYPE_FLOAT,
    _F.TYPE_UINT64,
    _F.TYPE_UINT32,
    _F.TYPE_INT64,
    _F.TYPE_BOOL,
    _F.TYPE_STRING,
    _F.TYPE_BYTES,
)
REPEATED = "repeated"

# message name -> its fields in order: (name, type, [REPEATED]); a str type names another message.
FieldSpec = tuple[Any, ...]
MESSAGES: dict[str, list[FieldSpec]] = {
    # /run/info: once at the start (and again every few seconds for a late live viewer)
    "RunInfo": [
        ("log_format_version", UINT32),
        ("package_version", STRING),  # oibar.__version__
        ("protocol_version", UINT32),  # the MCU link's PROTOCOL_VERSION
        ("model_path", STRING),
        ("model_version", STRING),
        ("model_sha256", STRING),  # of the ONNX file: replay says when it runs another model
        ("model_text", STRING),  # oibar --version's model line (far network, first pass)
        ("onnxruntime_version", STRING),
        ("ort_intra_op_threads", UINT32),  # replay must use the same count to be exact
        ("python_version", STRING),
        ("platform", STRING),
        ("hostname", STRING),
        ("camera", STRING),  # the frame source's name
        ("rate_hz", DOUBLE),
        ("wall_clock_start_s", DOUBLE),  # time.time() at t_s = 0
        ("intrinsics", "Intrinsics"),
        ("range_limits_m", DOUBLE, REPEATED),
        ("command_line", STRING),
    ],
    # The camera that takes the frames as recorded (its calibration when one is in use, else the
    # model's canonical camera); replay rebuilds the same remap from these numbers.
    "Intrinsics": [
        ("width_px", UINT32),
        ("height_px", UINT32),
        ("K", DOUBLE, REPEATED),  # 3x3, row-major, OpenCV pixel convention
        ("dist", DOUBLE, REPEATED),  # OpenCV's distortion vector; empty: none
        ("calibrated", BOOL),  # from a --calibration file (else the canonical camera)
        ("calibration_source", STRING),
        ("canonical_K", DOUBLE, REPEATED),  # the network's canonical camera, 3x3
        ("canonical_width_px", UINT32),
        ("canonical_height_px", UINT32),
    ],
    # /nav/cycle: one per navigation cycle, with what replay feeds the navigator again
    "Cycle": [
        ("cycle", UINT64),
        ("t_s", DOUBLE),  # cycle start, daemon clock (s since the run's start)
        ("has_frame", BOOL),
        ("frame_seq", UINT64),  # the camera's own counter (restarts when it is reopened)
        ("frame_t_s", DOUBLE),  # the frame's capture time on the daemon clock
        ("odometry", "Odometry"),
        ("hold_reason", STRING),
        ("link_up", BOOL),
        ("mcu_state", STRING),
        ("cycle_ms", DOUBLE),
        ("timings", "Timing", REPEATED),
        ("request_results", "RequestResult", REPEATED),
        ("corrupt_frames", UINT64),  # skipped by the source so far
        ("camera_error", STRING),
        ("vehicle_attitude", "VehicleAttitude"),  # with the cycle's frame only
    ],
    "Odometry": [  # the vehicle's relative velocity as fed to the navigator
        ("t_s", DOUBLE),
        ("v_D_mps", DOUBLE, REPEATED),
        ("sigma_mps", DOUBLE),
        ("malformed", STRING),  # repr of what the vehicle gave when it was not (t, v, sigma)
        ("reason", STRING),  # the filter's verdict: fused | gated | ... | dropped
    ],
    # the vehicle's relative attitude as fed to the navigator, and the integrity check's verdict
    "VehicleAttitude": [
        ("t_s", DOUBLE),
        ("att_rad", DOUBLE, REPEATED),  # the attitude error in D (rotation vector)
        ("sigma_rad", DOUBLE),
        ("malformed", STRING),  # repr of what the vehicle gave when it was not (t, att, sigma)
        ("checked", BOOL),  # the frame was checked against it (a fused frame)
        ("disagreement_deg", DOUBLE),  # camera's attitude against the vehicle's
        ("limit_deg", DOUBLE),
        ("replaced", BOOL),  # the frame was fused with the vehicle's attitude
    ],
    "Timing": [("name", STRING), ("ms", DOUBLE)],
    "RequestResult": [
        ("label", STRING),
        ("accepted", BOOL),
        ("reason", STRING),
        ("state", STRING),
    ],
    # /nav/estimate: the pose estimator's answer for the cycle's frame
    "PoseEstimate": [
        ("cycle", UINT64),
        ("frame_t_s", DOUBLE),
        ("frame_seq", UINT64),
        ("T_cam_target_m", DOUBLE, REPEATED),
        ("q_cam_target_wxyz", DOUBLE, REPEATED),
        ("confidence", DOUBLE),
        ("camera_range_m", DOUBLE),
        ("ortho_defect", DOUBLE),
        ("flags", STRING, REPEATED),
        ("latency_ms", DOUBLE),
        ("T_meas_cam_target_m", DOUBLE, REPEATED),  # the prior-free pose the filter fuses
        ("R_meas_cam_target", DOUBLE, REPEATED),  # 3x3 row-major
        ("error", STRING),  # the frame was refused (malformed, stale): why
        ("crops", UINT32),  # crop windows read through the keypoint networks: a slow cycle's cause
    ],
    # /nav/filter: the navigation filter at the cycle's time, with its 1-sigma uncertainties
    "FilterState": [
        ("cycle", UINT64),
        ("t_s", DOUBLE),
        ("valid", BOOL),
        ("initialised", BOOL),
        ("r_D_m", DOUBLE, REPEATED),
        ("v_D_mps", DOUBLE, REPEATED),
        ("att_rad", DOUBLE, REPEATED),
        ("w_rad_s", DOUBLE, REPEATED),
        ("pos_sigma_m", DOUBLE, REPEATED),
        ("vel_sigma_mps", DOUBLE, REPEATED),
        ("att_sigma_deg", DOUBLE, REPEATED),
        ("since_update_s", DOUBLE),
        ("range_m", DOUBLE),
        ("closing_speed_mps", DOUBLE),
        ("lateral_m", DOUBLE),
        ("misalignment_deg", DOUBLE),
        ("T_cam_target_m", DOUBLE, REPEATED),
        ("q_cam_target_wxyz", DOUBLE, REPEATED),
        ("update_reason", STRING),  # the frame's verdict: initialised | fused | gated | ...
        ("accepted", BOOL),
        ("gated", BOOL),
        ("reinitialised", BOOL),
        ("nis_pos", DOUBLE),
        ("nis_att", DOUBLE),
        ("velocity_reason", STRING),  # the odometry's verdict
        ("hold_reason", STRING),
    ],
    # /guidance/command: what guidance decided this cycle
    "GuidanceCommand": [
        ("cycle", UINT64),
        ("t_s", DOUBLE),
        ("phase", STRING),
        ("v_sp_D_mps", DOUBLE, REPEATED),
        ("w_sp_rad_s", DOUBLE, REPEATED),
        ("request", STRING),  # the mechanism request submitted this cycle (label), if any
        ("request_kind", STRING),
        ("opcode", UINT32),
        ("target_kpa", DOUBLE),
        ("param_id", UINT32),
        ("param_value", DOUBLE),
        ("nav_valid", BOOL),  # the NavUpdate sent to the MCU says valid
    ],
}


def _file_descriptor() -> Any:
    fdp = descriptor_pb2.FileDescriptorProto(name=FILE_NAME, package=PACKAGE, syntax="proto3")
    for name, fields in MESSAGES.items():
        msg = fdp.message_type.add(name=name)
        for number, spec in enumerate(fields, 1):
            fname, ftype = spec[0], spec[1]
            label = _F.LABEL_REPEATED if REPEATED in spec[2:] else _F.LABEL_OPTIONAL
            if isinstance(ftype, str):
                msg.field.add(
                    name=fname,
                    number=number,
                    label=label,
                    type=_F.TYPE_MESSAGE,
                    type_name=f".{PACKAGE}.{ftype}",
                )
            else:
                msg.field.add(name=fname, number=number, label=label, type=ftype)
    return fdp


FILE_DESCRIPTOR = _file_descriptor()


def _message_class(pool: Any, full_name: str) -> Any:
    desc = pool.FindMessageTypeByName(full_name)
    get = getattr(message_factory, "GetMessageClass", None)  # protobuf >= 4.22
    if get is not None:
        return get(desc)
    return message_factory.MessageFactory(pool).GetPrototype(desc)


_POOL = descriptor_pool.DescriptorPool()
_POOL.Add(FILE_DESCRIPTOR)
CLASSES: dict[str, Any] = {name: _message_class(_POOL, f"{PACKAGE}.{name}") for name in MESSAGES}


def new(name: str, **fields: Any) -> Any:
    """A new ``oibar.log.<name>`` message."""
    return CLASSES[name](**fields)


def schema_data(message_class_or_file: Any) -> bytes:
    """The serialised ``FileDescriptorSet`` of a message's file and every file it imports
    (dependencies first): what an MCAP protobuf schema record holds."""
    if isinstance(message_class_or_file, descriptor_pb2.FileDescriptorProto):
        own: bytes = descriptor_pb2.FileDescriptorSet(file=[message_class_or_file]).SerializeToString()
        return own
    desc_file = message_class_or_file.DESCRIPTOR.file
    files: list[Any] = []
    seen: set[str] = set()

    def add(fd: Any) -> None:
        if fd.name in seen:
            return
        seen.add(fd.name)
        for dep in fd.dependencies:
            add(dep)
        proto = descriptor_pb2.FileDescriptorProto()
        fd.CopyToProto(proto)
        files.append(proto)

    add(desc_file)
    data: bytes = descriptor_pb2.FileDescriptorSet(file=files).SerializeToString()
    return data


OWN_SCHEMA_DATA = schema_data(FILE_DESCRIPTOR)


class DecodeError(ValueError):
    """A message or schema that cannot be decoded."""


class ProtobufDecoder:
    """Decodes the protobuf messages of any MCAP channel from the ``FileDescriptorSet`` its
    schema record carries (the file's own description, not this build's), one pool per schema."""

    def __init__(self) -> None:
        self._classes: dict[tuple[int, str], Any] = {}

    def message_class(self, schema_id: int, name: str, data: bytes) -> Any:
        key = (schema_id, name)
        cls = self._classes.get(key)
        if cls is None:
            try:
                fds = descriptor_pb2.FileDescriptorSet.FromString(data)
                pool = descriptor_pool.DescriptorPool()
                pending = list(fds.file)
                added: set[str] = set()
                # dependencies first, whatever order the writer listed them in
                while pending:
                    ready = [f for f in pending if all(d in added for d in f.dependency)]
                    if not ready:
                        raise DecodeError(f"schema {name}: unresolved imports {pending[0].dependency}")
                    for f in ready:
                        pool.Add(f)
                        added.add(f.name)
                        pending.remove(f)
                cls = _message_class(pool, name)
            except DecodeError:
                raise
            except Exception as exc:  # protobuf raises TypeError/KeyError/DecodeError of its own
                raise DecodeError(f"schema {name}: not a protobuf FileDescriptorSet ({exc})") from exc
            self._classes[key] = cls
        return cls

    def decode(self, schema_id: int, name: str, schema_data: bytes, message: bytes) -> Any:
        cls = self.message_class(schema_id, name, schema_data)
        try:
            return cls.FromString(message)
        except Exception as exc:
            raise DecodeError(f"a {name} message cannot be decoded ({exc})") from exc
