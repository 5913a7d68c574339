"""The keypoint network: a crop window of the frame in, the fixture's keypoints (and the crop's
attitude head) out. One network, or two (a far network reading the windows of a distant
fixture); extra readings of the same window (its mirror, turned copies) averaged; the fixture's
sharp corners moved onto the frame's own.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from oibar.geometry.camera import project_target_points as project
from oibar.geometry.rotations import matrix_to_quat, mean_quat, quat_to_matrix
from oibar.nav.keypoints import (
    MIRROR_ATT,
    CropWindow,
    attitude_from_crop,
    cut,
    image_roll_rad,
    mirror_crop_px,
    mirror_permutation,
    mirror_symmetric_attitude,
    refine_corners_px,
    window_around,
)
from oibar.nav.pose.frames import to_input
from oibar.nav.pose.model_file import ModelFileError, export_flag, open_session, read_metadata

# The thresholds in crop pixels (here, in fusion and in search) were measured on models reading
# a 128 px crop. A model with another crop size (`oibar.crop.out_px`) reads the same fixture over
# more or fewer pixels, so it is held to the same fraction of its crop: every threshold is in
# pixels of a CROP_REF_PX crop.
CROP_REF_PX = 128
# Mirror reading (read_crop): on the fixture the two readings of a keypoint agree to 0.2 crop px
# (median; 99 % within 1.0, 99.9 % within 2.9: validation frames, 0.8.1). Averaging a crop of
# anything else with its mirror makes a left-right symmetric pattern that PnP takes for an
# aligned fixture (va012's cold start: 96 % range errors at confidence 0.96), so a keypoint whose
# readings disagree by more than this is not there.
MIRROR_AGREE_CROP_PX = 2.0
# A keypoint is where its heat map is tight. On the fixture the spread (the heat map's width,
# CROP_REF_PX terms) is 5.7 px (median; max 6.8 for 0.8.1 and 7.4 for 0.11.0 over 15 500 keypoints
# in windows cut around the true pose on every validation scene, every 9th frame). A crop of the
# station's structure can still give a few keypoints that PnP fits within the strong-fit bound:
# on va012's cold start (the first pass takes the 10 m fixture for a 0.45 m one) 0.11.0's fit of
# six keypoints spread 8.5-25 px answered 0.42 m at confidence 0.94. Broader than this: not there.
# That is the gate of a network trained on exact labels; one trained on measured ones learns heat
# maps as broad as their noise (the lab fine-tune, labelled through motion capture: 13-18 px on
# the fixture, every keypoint gated), so an export may carry its own gate
# (``oibar.pnp.max_spread_crop_px``), and every spread it reports is read in this gate's terms
# (`spread_scale`), so that the search's likeness scores and floors hold for it too.
MAX_SPREAD_CROP_PX = 9.0
# The largest turn of the refining pass's extra readings: the network was trained on crops
# turned up to 15 deg (kp_data.CropAugment.angle_deg); beyond, it reads crops it never saw.
MAX_TURNED_READING_DEG = 15.0
# The refining pass's sub-pixel corners (``oibar.corner_refine_side_px``): the keypoints refined
# (the fixture's sharp corners: the rim's and the connector's; with the connector's too, 0.15.0's
# validation attitude at 0-1 / 1-2 m is 0.53 / 0.48 deg, against 0.62 / 0.57 with the rim's alone
# and 0.65 / 0.66 with none: every 8th frame), cornerSubPix's half window per pixel of the
# fixture's extent (the rim band is 6 % of it: 5 px at 0.5 m, where the fixture spans ~270 px),
# its bounds, and how far a corner may move per pixel of half window before the search is taken
# to have found another corner.
CORNER_NAMES = (
    "rim_top_left",
    "rim_top_right",
    "rim_bottom_right",
    "rim_bottom_left",
    "connector_top_left",
    "connector_top_right",
    "connector_bottom_right",
    "connector_bottom_left",
)
CORNER_HALF_WIN_PER_EXTENT = 0.02
CORNER_HALF_WIN_PX = (2, 6)
CORNER_MAX_MOVE_PER_HALF_WIN = 0.4
KEYPOINT_OUTPUTS = ("kp_crop_px", "kp_present")
# Windows placed by a pose are turned to show the fixture upright when the pose has it turned in
# the image by more than this. Every training set of the shipped network is unrolled: on the roll
# sweep val_roll (0.34.0, every frame alone) compliance was 100 % at 0 and 5 deg of roll, 90-94 %
# at 10-20, 50 % at 30 and 0 from 45, while the same network read the same frames in windows
# turned upright to 0.2-1.1 % / 2-6 deg at 90 and 180 deg (the approach's own error unrolled:
# docs/model_card.md). Within the 15 deg its crops were turned in training, turning gains nothing:
# from 7.5 deg on, the 10 deg scene read 3.97 -> 4.19 deg (frames beyond 5 deg 2 -> 6), the 15
# and 20 deg ones 3.81 -> 3.88 and 3.58 -> 3.69; from 15 deg on, the 10 deg scene is untouched.
# Below it the windows stay as they were, so everything measured on unrolled scenes (the
# campaigns' roll is +-5 deg) holds.
UPRIGHT_FROM_DEG = 15.0


def keypoint_gate(path: Path, meta: dict[str, Any]) -> float:
    """The export's keypoint gate (``oibar.pnp.max_spread_crop_px``, CROP_REF_PX terms), else
    MAX_SPREAD_CROP_PX; ModelFileError when it is not a spread > 0."""
    gate = meta["pnp"].get("max_spread_crop_px", MAX_SPREAD_CROP_PX)
    if isinstance(gate, bool) or not isinstance(gate, int | float) or not 0.0 < float(gate) < np.inf:
        raise ModelFileError(
            f"{path}: oibar.pnp.max_spread_crop_px must be a spread in crop pixels > 0, got {gate!r}"
        )
    return float(gate)


def upright_angle_rad(K: np.ndarray, R_cam_target: np.ndarray, T_cam_target_m: np.ndarray) -> float:
    """The turn (CropWindow.angle_rad) that shows a fixture at this pose upright in its crop: minus
    its image roll (image_roll_rad) beyond UPRIGHT_FROM_DEG, else 0 (the window as trained)."""
    roll = image_roll_rad(K, R_cam_target, T_cam_target_m)
    if not np.isfinite(roll) or abs(roll) <= np.radians(UPRIGHT_FROM_DEG):
        return 0.0
    return -roll


@dataclass
class CropReading:
    """What the keypoint network reads from one crop: keypoints in frame pixels (K, 2), NaN where
    absent; their spread (K,) crop px; presence (K,) 0..1; the attitude head's R_cam_target
    (None for a model without the head)."""

    uv_px: np.ndarray
    spread_crop_px: np.ndarray
    present: np.ndarray
    R_cam_target_head: np.ndarray | None = None
    # the untouched window's own keypoints when uv_px averages several readings (turned), else None
    untouched_uv_px: np.ndarray | None = None


class KeypointReader:
    """The keypoint network of a keypoint export (and its far network, ``oibar.far_network``),
    with the reading options the export chose (each may be overridden for studies):
    ``mirror`` (``oibar.mirror_reading``), ``turned_reading_deg`` and ``turned_reading_head``
    (``oibar.turned_reading_*``), ``corner_refine_side_px`` (``oibar.corner_refine_side_px``);
    ``upright`` (windows turned to a rolled fixture, UPRIGHT_FROM_DEG; off only for studies).
    A malformed export is a ModelFileError naming the file."""

    def __init__(
        self,
        path: Path,
        meta: dict[str, Any],
        threads: int,
        allow_spinning: bool,
        mirror: bool | None = None,
        turned_reading_deg: float | None = None,
        turned_reading_head: bool | None = None,
        corner_refine_side_px: float | None = None,
        upright: bool = True,
    ):
        self.path, self.meta = path, meta
        # windows turned to show a rolled fixture upright, and the search's roll checks (roll.UPRIGHT_TWIN)
        self.upright = bool(upright)
        self.session = open_session(path, threads, allow_spinning)
        self.input_name = self.session.get_inputs()[0].name
        self.output_names = [o.name for o in self.session.get_outputs()]
        missing = [n for n in KEYPOINT_OUTPUTS if n not in self.output_names]
        if missing:
            raise ModelFileError(f"{path}: outputs {missing} missing (has {self.output_names})")
        self.out_px = int(meta["crop"]["out_px"])
        self.margin = float(meta["crop"]["margin"])
        self.points_m = np.asarray(meta["keypoints_3d_m"], float)
        self.reproj_crop_px = float(meta["pnp"]["reproj_crop_px"])
        self.min_present = float(meta["pnp"]["min_present"])
        self.max_spread_crop_px = keypoint_gate(path, meta)  # CROP_REF_PX terms
        self.spread_scale = (
            MAX_SPREAD_CROP_PX / self.max_spread_crop_px
        )  # its spreads in MAX_SPREAD_CROP_PX's terms
        self.K_frame = np.array(meta["camera"]["K_frame"], float)
        self.R_att_ref = self._attitude_head()
        # each crop read with its mirror in the refining pass: as the export says (chosen per
        # network on the closed loop), unless told
        if mirror is None:
            mirror = bool(meta.get("mirror_reading", False))
        self.mirror = mirror_permutation(self.points_m) if mirror else None
        if mirror and (
            self.mirror is None
            or (self.R_att_ref is not None and not mirror_symmetric_attitude(self.R_att_ref))
        ):
            raise ModelFileError(
                f"{path}: the mirror reading needs a left-right symmetric keypoint set and "
                "attitude-head reference (oibar.keypoints_3d_m, oibar.attitude_head.R_ref); this "
                "model has not: export it without --mirror-reading"
            )
        # the refining pass's turned readings (chosen per network on validation and the closed loop)
        turned = meta.get("turned_reading_deg", 0.0) if turned_reading_deg is None else turned_reading_deg
        if (
            isinstance(turned, bool)
            or not isinstance(turned, int | float)
            or not 0.0 <= float(turned) <= MAX_TURNED_READING_DEG
        ):
            raise ModelFileError(
                f"{path}: oibar.turned_reading_deg must be a number of degrees in "
                f"[0, {MAX_TURNED_READING_DEG:g}] (0: read once), got {turned!r}"
            )
        self.turned_reading_deg = float(turned)
        # and whether the attitude head's answer is the mean of all of them or the untouched window's
        self.turned_reading_head = export_flag(path, meta, "turned_reading_head", turned_reading_head)
        # the refining pass's sub-pixel corners (chosen per network on validation)
        side = (
            meta.get("corner_refine_side_px", 0.0) if corner_refine_side_px is None else corner_refine_side_px
        )
        if isinstance(side, bool) or not isinstance(side, int | float) or not 0.0 <= float(side) < np.inf:
            raise ModelFileError(
                f"{path}: oibar.corner_refine_side_px must be a size in frame pixels >= 0 "
                f"(0: off), got {side!r}"
            )
        self.corner_refine_side_px = float(side)
        names = list(meta.get("keypoint_names") or [])
        self.corner_idx = np.array([names.index(n) for n in CORNER_NAMES if n in names], int)
        if self.corner_refine_side_px > 0 and len(self.corner_idx) != len(CORNER_NAMES):
            raise ModelFileError(
                f"{path}: the corner refinement needs the rim's and the connector's corners "
                f"among its keypoints (oibar.keypoint_names {list(CORNER_NAMES)}); this model "
                f"names {names}"
            )

    head_output = ""  # the attitude head's output name (set by _attitude_head when there is one)
    far_session: Any = None  # the far network's session (open_far_network); None: one network
    far_from_m = np.inf  # the head-on range from which it reads a window
    # crops read through the keypoint networks so far (every row of every batch: a crop read
    # with its mirror or turned counts each): what a frame's search cost, for its stage tally
    crops_read = 0

    def _attitude_head(self) -> np.ndarray | None:
        """R_ref of the attitude head (model >= 0.6.0), None for a model without one."""
        head = self.meta.get("attitude_head")
        if head is None:
            return None
        try:
            R_ref = np.asarray(head["R_ref"], float)
            name = str(head["output"])
        except (KeyError, TypeError, ValueError) as exc:
            raise ModelFileError(f"{self.path}: oibar.attitude_head is malformed ({exc})") from exc
        if R_ref.shape != (3, 3) or not np.allclose(R_ref @ R_ref.T, np.eye(3), atol=1e-6):
            raise ModelFileError(f"{self.path}: oibar.attitude_head.R_ref is not a rotation matrix")
        if name not in self.output_names:
            raise ModelFileError(f"{self.path}: the attitude head's output {name!r} is missing")
        self.head_output = name
        return R_ref

    def open_far_network(self, threads: int, allow_spinning: bool) -> None:
        """``oibar.far_network`` ({"file", "from_m"}): a second keypoint network, a file beside
        this one, that reads every crop window whose head-on range is `from_m` or more (one
        network of this size reads near or far well, not both: docs/model_history.md, "Candidate
        0.26.0"). It must be the same kind of network as this one: the same outputs, keypoints,
        crop and attitude head, since every table of this file's (fusion, error models, corner
        step) reads its answers too. Called last, so that a fault of this file's own is reported
        as this file's, not as a far network that no longer matches it."""
        spec = self.meta.get("far_network")
        if spec is None:
            return
        try:
            name, from_m = str(spec["file"]), spec["from_m"]
        except (KeyError, TypeError) as exc:
            raise ModelFileError(
                f"{self.path}: oibar.far_network must be {{'file': NAME, 'from_m': RANGE}}, got {spec!r}"
            ) from exc
        if (
            isinstance(from_m, bool)
            or not isinstance(from_m, int | float)
            or not 0.0 < float(from_m) < np.inf
        ):
            raise ModelFileError(
                f"{self.path}: oibar.far_network.from_m must be a range in m > 0, got {from_m!r}"
            )
        far = self.path.parent / name
        if Path(name).name != name or not far.is_file():
            raise ModelFileError(
                f"{self.path}: its far network {name!r} is missing (a file name; it must lie beside it)"
            )
        meta = read_metadata(far)
        for key in ("kind", "keypoints_3d_m", "keypoint_names", "crop", "attitude_head", "input_size_wh"):
            if meta.get(key) != self.meta.get(key):
                raise ModelFileError(
                    f"{far}: not the same kind of network as {self.path.name} (oibar.{key} differs), "
                    "so this file's tables cannot read it"
                )
        session = open_session(far, threads, allow_spinning)
        inputs = session.get_inputs()
        outputs = [o.name for o in session.get_outputs()]
        if outputs != self.output_names or [i.name for i in inputs] != [self.input_name]:
            raise ModelFileError(
                f"{far}: inputs/outputs {[i.name for i in inputs]} / {outputs} differ from "
                f"{self.path.name}'s {[self.input_name]} / {self.output_names}"
            )
        self.far_session, self.far_from_m = session, float(from_m)

    def warm_up(self, runs: int) -> None:
        """The first runs plan memory and pick kernels: keep them out of flight."""
        zero = np.zeros((1, 3, self.out_px, self.out_px), np.float32)
        for _ in range(runs):
            self.run(zero)
            if self.far_session is not None:
                self.far_session.run(None, {self.input_name: zero})

    # ------------------------------------------------------------------ geometry of the windows
    def window_for(
        self, R_cam_target: np.ndarray, T_cam_target_m: np.ndarray, upright: bool = True
    ) -> CropWindow | None:
        """The window around a pose's projected keypoints, turned so that the network sees the
        fixture upright where the pose has it turned beyond UPRIGHT_FROM_DEG in the image
        (upright_angle_rad; not with `upright` False or the reader's `upright` off); None where it
        projects nowhere (behind the camera)."""
        uv = project(self.K_frame, self.points_m, R_cam_target, T_cam_target_m)
        if not np.all(np.isfinite(uv)):
            return None
        angle = (
            upright_angle_rad(self.K_frame, R_cam_target, T_cam_target_m) if upright and self.upright else 0.0
        )
        return window_around(uv, self.out_px, self.margin, angle_rad=angle)

    def range_for_side_m(self, side_px: float) -> float:
        """The range at which the fixture, seen head-on, fills a window of side_px (its
        keypoints' larger extent across the boresight x the crop margin): the scale the range
        error models are read at when nothing else says how far the fixture is."""
        extent_m = float(np.max(np.ptp(self.points_m[:, :2], axis=0)))
        return float(self.K_frame[0, 0]) * extent_m * self.margin / max(side_px, 1e-6)

    # ------------------------------------------------------------------ reading windows
    def run(self, x: np.ndarray) -> dict[str, np.ndarray]:
        """Prepared crops (N, 3, S, S) float32 in [0, 1] -> the near network's outputs by name."""
        return dict(zip(self.output_names, self.session.run(None, {self.input_name: x}), strict=True))

    def reads_far(self, win: CropWindow) -> bool:
        """Whether the far network reads this window (its head-on range from `far_from_m` on)."""
        return self.far_session is not None and self.range_for_side_m(win.side_px) >= self.far_from_m

    def run_windows(self, x: np.ndarray, wins: list[CropWindow]) -> dict[str, np.ndarray]:
        """Crops (N, 3, S, S) of the windows `wins` (one per row) -> every output by name, each
        row read by the network for its window's range (`reads_far`); one network, one batch,
        without a far network."""
        self.crops_read += len(x)
        if self.far_session is None:
            return self.run(x)
        far = np.array([self.reads_far(w) for w in wins], bool)
        if not far.any():
            return self.run(x)
        far_out = dict(
            zip(self.output_names, self.far_session.run(None, {self.input_name: x[far]}), strict=True)
        )
        if far.all():
            return far_out
        near_out = self.run(x[~far])
        out = {}
        for k, v in near_out.items():
            both = np.empty((len(wins),) + v.shape[1:], v.dtype)
            both[~far], both[far] = v, far_out[k]
            out[k] = both
        return out

    def read_crop(self, image: np.ndarray, win: CropWindow, refining: bool = False) -> CropReading:
        """One window through the keypoint network (CropReading). In the refining pass
        (`refining`: a window cut around a strong fit) the export can ask for more readings of
        the same window, all in one batch, averaged in frame pixels:

        - its mirror image (``oibar.mirror_reading``, a left-right symmetric fixture,
          `self.mirror`): the mirror's reading mapped back (u -> S - u, each keypoint from its
          twin, the head's rotation vector turned over), so the network's own left-right leaning
          cancels. 0.8.1 reads a -0.24 deg tilt about y on every validation frame at 2-5 m and
          +0.12 deg in the mirror; averaged, -0.06 deg.
        - the window turned by +-``oibar.turned_reading_deg`` about its centre (a camera rolled
          about its boresight: the network was trained on crops turned up to 15 deg). Each
          reading's keypoints go back to the frame through its own window; a keypoint counts
          where most readings see it. 0.8.1 at 8 deg: validation attitude 0.84 -> 0.81 deg, the
          filter's measurement 0.86 -> 0.82. With ``oibar.turned_reading_head`` the attitude
          head's answer is the mean of the readings' (each mapped to the camera through its own
          window), else the untouched window's: 0.15.3 at 8 deg on validation, 0.539 -> 0.531
          deg. The untouched window's own keypoints ride along (`untouched_uv_px`) for the
          filter's prior-free fit (``oibar.turned_reading_measurement``).

        Only for a window already known to hold the fixture: averaged with its mirror, a crop of
        anything makes a symmetric pattern that PnP fits well."""
        wins = [win]
        if refining and self.turned_reading_deg > 0:
            a = float(np.radians(self.turned_reading_deg))
            wins += [replace(win, angle_rad=win.angle_rad + a), replace(win, angle_rad=win.angle_rad - a)]
        mirror = refining and self.mirror is not None
        crops = [cut(image, w) for w in wins]
        batch = [c for crop in crops for c in ((crop, crop[:, ::-1]) if mirror else (crop,))]
        rows = [w for w in wins for _ in range(2 if mirror else 1)]
        out = {k: v.astype(float) for k, v in self.run_windows(to_input(np.stack(batch)), rows).items()}
        per = 2 if mirror else 1
        readings = [
            self._reading(w, {k: v[i * per : (i + 1) * per] for k, v in out.items()})
            for i, w in enumerate(wins)
        ]
        if len(readings) == 1:
            return readings[0]
        uv = np.stack([r.uv_px for r in readings])
        seen = np.isfinite(uv[..., 0])
        mean_uv = np.full_like(readings[0].uv_px, np.nan)
        keep = seen.sum(0) * 2 > len(readings)
        for j in np.flatnonzero(keep):
            mean_uv[j] = uv[seen[:, j], j].mean(0)
        return CropReading(
            mean_uv,
            np.mean([r.spread_crop_px for r in readings], axis=0),
            np.mean([r.present for r in readings], axis=0),
            self._head_of(readings),
            readings[0].uv_px,
        )

    def _head_of(self, readings: list[CropReading]) -> np.ndarray | None:
        """The attitude head's answer for read_crop's readings: the untouched window's (the
        first), or with `turned_reading_head` the mean of every reading that has one."""
        if not self.turned_reading_head:
            return readings[0].R_cam_target_head
        heads = [r.R_cam_target_head for r in readings if r.R_cam_target_head is not None]
        if len(heads) < 2:
            return heads[0] if heads else None
        R: np.ndarray = quat_to_matrix(mean_quat(np.stack([matrix_to_quat(h) for h in heads])))
        return R

    def _reading(self, win: CropWindow, out: dict[str, np.ndarray]) -> CropReading:
        """The network's outputs for one window (one row, or two: the crop and its mirror image,
        averaged as read_crop says) -> CropReading, keypoints in frame pixels."""
        if len(out["kp_crop_px"]) == 1:
            out = {k: v[0] for k, v in out.items()}
        else:
            assert self.mirror is not None  # two rows only for a mirror reading
            disagree = None
            for k in out:
                if k == "kp_crop_px":
                    m = mirror_crop_px(out[k][1], self.mirror, self.out_px)
                    disagree = (
                        np.linalg.norm(out[k][0] - m, axis=1)
                        > MIRROR_AGREE_CROP_PX * self.out_px / CROP_REF_PX
                    )
                elif self.R_att_ref is not None and k == self.head_output:
                    m = out[k][1] * MIRROR_ATT
                else:  # per keypoint: presence, spread
                    m = out[k][1][self.mirror]
                out[k] = 0.5 * (out[k][0] + m)
            if disagree is not None:
                out["kp_present"][disagree] = 0.0
        kp = out["kp_crop_px"]
        present = out["kp_present"]
        spread = out["kp_spread_px"] if "kp_spread_px" in out else np.zeros(len(kp))
        uv = win.to_frame(kp)
        uv[(present < self.min_present) | (spread > self.max_spread_crop_px * self.out_px / CROP_REF_PX)] = (
            np.nan
        )
        R_head = None
        if self.R_att_ref is not None:
            att = out[self.head_output]
            if np.all(np.isfinite(att)):
                R_head = attitude_from_crop(win, self.K_frame, att, self.R_att_ref)
        return CropReading(uv, spread, present, R_head)

    def fixture_likeness(self, image: np.ndarray, wins: list[CropWindow]) -> np.ndarray:
        """How much each window looks like the fixture, read in one batch: mean presence x
        exp(-mean heat-map spread / 4 px, CROP_REF_PX terms)."""
        present, spread = self._presence_and_spread(image, wins)
        score: np.ndarray = present * np.exp(-(np.zeros(len(wins)) if spread is None else spread) / 4.0)
        return score

    def heat_spread(self, image: np.ndarray, wins: list[CropWindow]) -> np.ndarray | None:
        """Each window's mean heat-map spread (CROP_REF_PX terms), read in one batch; None for a
        network without the spread output. The fixture's keypoints are tightest in a crop that
        shows it as trained (upright): roll.UPRIGHT_TWIN."""
        return self._presence_and_spread(image, wins)[1]

    def _presence_and_spread(
        self, image: np.ndarray, wins: list[CropWindow]
    ) -> tuple[np.ndarray, np.ndarray | None]:
        """Each window's mean keypoint presence and mean heat-map spread (CROP_REF_PX terms, and in
        MAX_SPREAD_CROP_PX's: `spread_scale`; None without that output), one batch."""
        out = self.run_windows(np.concatenate([to_input(cut(image, w)) for w in wins]), wins)
        present = out["kp_present"].astype(float).mean(axis=1)
        if "kp_spread_px" not in out:
            return present, None
        return present, out["kp_spread_px"].astype(float).mean(
            axis=1
        ) * CROP_REF_PX / self.out_px * self.spread_scale

    def refined_corners(self, image: np.ndarray, win: CropWindow, uv: np.ndarray) -> np.ndarray:
        """The fixture's sharp corners (CORNER_NAMES: the rim's, the connector's) moved onto the
        frame's own (keypoints.refine_corners_px) when the fixture spans at least
        `corner_refine_side_px` frame pixels (its window's side over the crop margin); the search
        window scales with it so that it stays inside the rim band and the connector (6 % and
        8 % of the fixture's width). Off (the keypoints as read) when the export says 0."""
        import cv2

        extent_px = win.side_px / self.margin
        if self.corner_refine_side_px <= 0 or extent_px < self.corner_refine_side_px:
            return uv
        half = int(np.clip(round(CORNER_HALF_WIN_PER_EXTENT * extent_px), *CORNER_HALF_WIN_PX))
        gray = cv2.cvtColor(np.ascontiguousarray(image), cv2.COLOR_RGB2GRAY)
        out, _ = refine_corners_px(gray, uv, self.corner_idx, half, CORNER_MAX_MOVE_PER_HALF_WIN * half)
        return out
