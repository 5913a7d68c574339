"""Synthetic calibration recordings with known transforms, for validation and for trying the
toolbox without a lab: a mocap CSV, rendered frames of the berthing fixture with a ChArUco
board on its rim face, the frame index, the pattern and intrinsics files, and the truth.

The fixture is drawn by the project's renderer (oibar_hil.render); the renderer has no
textures, so the board is projected with the same camera model and composited into each
frame (2x supersampled, then area-averaged), before blur and read noise.

It lives in the simulator package because it renders: the lab toolbox (oibar.calib) itself
imports no simulator.

CLI: python -m oibar_hil.calib_synth OUT_DIR [--poses 150] [--seed 1]
"""

from __future__ import annotations

import argparse
import json
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from oibar.calib.pnp import Intrinsics, Pattern
from oibar.geometry.rotations import matrix_to_quat as R_to_quat_wxyz
from oibar.geometry.transforms import T_from_vec, inv_T, make_T


def _T(t_m, rotvec_deg) -> np.ndarray:
    return T_from_vec(np.concatenate([np.asarray(t_m, float), np.radians(rotvec_deg)]))


def default_pattern() -> Pattern:
    # 7 x 5 squares of 65 mm (0.455 x 0.325 m) on the 0.50 x 0.36 m rim face, 1 mm proud of it.
    sx, sy, sq = 7, 5, 0.065
    return Pattern(sx, sy, sq, 0.048, "DICT_4X4_50", make_T(np.eye(3), [-sx * sq / 2, -sy * sq / 2, -0.001]))


@dataclass
class SynthConfig:
    n_frames: int = 200
    frame_rate_hz: float = 10.0
    mocap_rate_hz: float = 100.0
    offset_s: float = 0.0237  # mocap time = frame time + offset_s
    frame_t0_s: float = 5.0  # the camera clock starts elsewhere than the mocap's
    sigma_t_m: float = 0.2e-3  # mocap noise per sample: RMS position error
    sigma_r_deg: float = 0.5  # and RMS rotation angle (per axis: / sqrt(3))
    noise_dn: float = 2.0  # image read noise
    blur_px: float = 0.6
    seed: int = 1
    # Truth: camera in the housing markers' frame, target in the target markers' frame.
    T_housing_cam: np.ndarray = field(default_factory=lambda: _T([0.035, -0.062, 0.048], [12.0, -95.0, 7.0]))
    T_tmarkers_target: np.ndarray = field(
        default_factory=lambda: _T([0.21, -0.14, 0.09], [-60.0, 20.0, 150.0])
    )
    T_mocap_target0: np.ndarray = field(default_factory=lambda: _T([1.2, 0.4, 1.1], [90.0, 0.0, 0.0]))
    pattern: Pattern = field(default_factory=default_pattern)


def T_target_cam_at(tau_s: np.ndarray, cfg: SynthConfig) -> np.ndarray:
    """The calibration motion: the camera sweeps a spherical cap in front of the board
    (azimuth +-35 deg, elevation +-25 deg, 0.75-1.25 m) looking near its centre, with +-30 deg
    of roll, at incommensurate frequencies so that rotations about all axes are mixed."""
    tau = np.atleast_1d(tau_s)
    rng = np.random.default_rng(cfg.seed)
    ph = rng.uniform(0, 2 * np.pi, 6)
    az = np.radians(35) * np.sin(2 * np.pi * 0.110 * tau + ph[0])
    el = np.radians(25) * np.sin(2 * np.pi * 0.173 * tau + ph[1])
    dist = 1.0 + 0.25 * np.sin(2 * np.pi * 0.071 * tau + ph[2])
    roll = np.radians(30) * np.sin(2 * np.pi * 0.131 * tau + ph[3])
    look = np.stack(
        [
            0.04 * np.sin(2 * np.pi * 0.29 * tau + ph[4]),
            0.03 * np.sin(2 * np.pi * 0.23 * tau + ph[5]),
            np.zeros_like(tau),
        ],
        1,
    )
    p = np.stack([np.sin(az) * np.cos(el), np.sin(el), -np.cos(az) * np.cos(el)], 1) * dist[:, None]
    z = look - p
    z /= np.linalg.norm(z, axis=1, keepdims=True)
    x0 = np.cross(np.array([0.0, 1.0, 0.0]), z)  # camera +Y roughly along the target's +Y
    x0 /= np.linalg.norm(x0, axis=1, keepdims=True)
    y0 = np.cross(z, x0)
    c, s = np.cos(roll)[:, None], np.sin(roll)[:, None]
    x, y = c * x0 + s * y0, -s * x0 + c * y0
    out = np.zeros((len(tau), 4, 4))
    out[:, :3, :3] = np.stack([x, y, z], 2)
    out[:, :3, 3] = p
    out[:, 3, 3] = 1.0
    return out


def T_mocap_target_at(tau_s: np.ndarray, cfg: SynthConfig) -> np.ndarray:
    """The target moves too (a slow wobble of a few degrees and centimetres), so that both
    rigid bodies move as in a real recording."""
    tau = np.atleast_1d(tau_s)
    wob = np.zeros((len(tau), 4, 4))
    wob[:, :3, :3] = Rotation.from_rotvec(
        np.radians(np.stack([4 * np.sin(0.37 * tau), 3 * np.sin(0.29 * tau), 5 * np.sin(0.19 * tau)], 1))
    ).as_matrix()
    wob[:, :3, 3] = np.stack(
        [0.03 * np.sin(0.3 * tau), 0.02 * np.sin(0.41 * tau), 0.01 * np.sin(0.23 * tau)], 1
    )
    wob[:, 3, 3] = 1.0
    return cfg.T_mocap_target0 @ wob


def body_noise(T: np.ndarray, rng, sigma_t_m: float, sigma_r_rad: float) -> np.ndarray:
    """Each pose of (n, 4, 4) `T` perturbed in its body frame, per axis sigma_t_m and sigma_r_rad:
    the mocap's per-sample noise (oibar_hil.lab_recording draws its runs' with it too)."""
    d = np.concatenate([rng.normal(0, sigma_t_m, (len(T), 3)), rng.normal(0, sigma_r_rad, (len(T), 3))], 1)
    E = np.zeros((len(T), 4, 4))
    E[:, :3, :3] = Rotation.from_rotvec(d[:, 3:]).as_matrix()
    E[:, :3, 3] = d[:, :3]
    E[:, 3, 3] = 1.0
    return T @ E


def frame_times(cfg: SynthConfig) -> np.ndarray:
    """Frame time stamps: nominal rate plus +-3 ms of trigger jitter (recorded exactly), as
    from a free-running USB camera; the clocks of camera and mocap do not tick in step."""
    jitter = np.random.default_rng(cfg.seed + 2000).uniform(-0.003, 0.003, cfg.n_frames)
    return cfg.frame_t0_s + np.arange(cfg.n_frames) / cfg.frame_rate_hz + jitter


def mocap_samples(cfg: SynthConfig) -> dict:
    """Both rigid bodies sampled at the mocap rate over the frames' span (+1 s each side),
    with per-sample noise in the body frame."""
    t_f = frame_times(cfg) + cfg.offset_s
    tau = np.arange(
        np.floor((t_f[0] - 1.0) * cfg.mocap_rate_hz), np.ceil((t_f[-1] + 1.0) * cfg.mocap_rate_hz) + 1
    )
    tau = tau / cfg.mocap_rate_hz
    rng = np.random.default_rng(cfg.seed + 1000)
    T_mt = T_mocap_target_at(tau, cfg)
    T_mc = T_mt @ T_target_cam_at(tau, cfg)
    housing = T_mc @ inv_T(cfg.T_housing_cam)
    tmarkers = T_mt @ inv_T(cfg.T_tmarkers_target)
    st, sr = cfg.sigma_t_m / np.sqrt(3), np.radians(cfg.sigma_r_deg) / np.sqrt(3)
    return {
        "t_s": tau,
        "housing": body_noise(housing, rng, st, sr),
        "tmarkers": body_noise(tmarkers, rng, st, sr),
    }


def write_mocap_csv(path: Path, mocap: dict, names=("housing", "tmarkers")) -> None:
    """Long layout, one row per sample and rigid body (see docs/calibration.md); a pose of NaN
    (an occluded sample) is written as a row of NaN."""
    lines = ["time_s,body,x_m,y_m,z_m,qw,qx,qy,qz"]
    for k, t in enumerate(mocap["t_s"]):
        for name in names:
            T = mocap[name][k]
            if not np.isfinite(T[0, 0]):
                lines.append(f"{t:.4f},{name}," + ",".join(["NaN"] * 7))
                continue
            q = R_to_quat_wxyz(T[:3, :3])
            lines.append(
                f"{t:.4f},{name},"
                + ",".join(f"{v:.6f}" for v in T[:3, 3])
                + ","
                + ",".join(f"{v:.8f}" for v in q)
            )
    path.write_text("\n".join(lines) + "\n")


class BoardCompositor:
    """Draws the board into a rendered frame with the camera model (no renderer textures)."""

    def __init__(self, pattern: Pattern, intr: Intrinsics, px_per_m: float = 4000.0):
        w_m, h_m = pattern.size_m
        self.m_per_px = 1.0 / px_per_m
        self.img = pattern.board().generateImage(
            (int(round(w_m * px_per_m)), int(round(h_m * px_per_m))), marginSize=0, borderBits=1
        )
        self.pattern, self.intr = pattern, intr

    def composite(self, frame_rgb: np.ndarray, T_cam_pattern: np.ndarray) -> np.ndarray:
        s = 2  # supersampling
        K2 = self.intr.K.copy()
        K2[:2] *= s
        K2[0, 2] += (s - 1) / 2  # pixel-centre convention at s times the resolution
        K2[1, 2] += (s - 1) / 2
        # Board image pixel (u, v) -> pattern metres ((u + 0.5) m, (v + 0.5) m, 0) -> camera.
        S = np.array(
            [[self.m_per_px, 0, 0.5 * self.m_per_px], [0, self.m_per_px, 0.5 * self.m_per_px], [0, 0, 1]]
        )
        R, t = T_cam_pattern[:3, :3], T_cam_pattern[:3, 3]
        Hm = K2 @ np.column_stack([R[:, 0], R[:, 1], t]) @ S
        W, H = self.intr.width_px * s, self.intr.height_px * s
        # Printed board: white ~0.8, black ~0.1 reflectance under the lab light.
        shade = 25 + self.img.astype(np.float32) * (190 - 25) / 255.0
        board = cv2.warpPerspective(shade, Hm, (W, H), flags=cv2.INTER_AREA, borderValue=0)
        mask = cv2.warpPerspective(np.ones_like(shade), Hm, (W, H), flags=cv2.INTER_LINEAR, borderValue=0)
        board = cv2.resize(board, (W // s, H // s), interpolation=cv2.INTER_AREA)
        mask = cv2.resize(mask, (W // s, H // s), interpolation=cv2.INTER_AREA)[..., None]
        out = frame_rgb.astype(np.float32) * (1 - mask) + board[..., None] * mask
        return np.clip(out + 0.5, 0, 255).astype(np.uint8)


def render_frames(cfg: SynthConfig, intr: Intrinsics, out_dir: Path | None = None) -> list:
    """Render the frames (RGB uint8); also written as PNG to out_dir/frames when given."""
    import os

    os.environ.setdefault("LP_NUM_THREADS", "2")
    from oibar.geometry.camera import PinholeCamera

    from .meshes import berthing_fixture
    from .render import Renderer, RenderSettings, apply_sensor_effects

    cam = PinholeCamera()
    r = Renderer(cam, RenderSettings(shadow_map_px=1024))
    try:
        r.load_scene(berthing_fixture(), "iss", np.zeros(3))
        comp = BoardCompositor(cfg.pattern, intr)
        tau = frame_times(cfg) + cfg.offset_s
        T_tc = T_target_cam_at(tau, cfg)
        sun_target = np.array([0.3, -0.5, -1.0])  # towards the light: behind and above the camera
        images = []
        for k in range(cfg.n_frames):
            # Earth put behind the camera: a black lab background.
            img = r.render(
                T_tc[k, :3, :3], T_tc[k, :3, 3], sun_target, earth_center_lvlh_km=-6791.0 * T_tc[k, :3, 2]
            )
            T_cp = inv_T(T_tc[k]) @ cfg.pattern.T_target_pattern
            img = comp.composite(img, T_cp)
            rng = np.random.default_rng([cfg.seed, k])
            img = apply_sensor_effects(img, cfg.noise_dn, cfg.blur_px, rng)
            images.append(img)
            if out_dir is not None:
                cv2.imwrite(
                    str(out_dir / "frames" / f"{k:06d}.png"), img[..., ::-1], [cv2.IMWRITE_PNG_COMPRESSION, 1]
                )
    finally:
        r.release()
    return images


# Corner noise per image axis measured on the rendered frames (PnP residuals 0.14 px RMS,
# docs/calibration.md); the simulated observations use a little more, to stay on the safe side.
SIM_CORNER_SIGMA_PX = 0.12


def simulate_observations(
    cfg: SynthConfig, intr: Intrinsics, corner_sigma_px: float = SIM_CORNER_SIGMA_PX, margin_px: float = 4.0
) -> list:
    """What the detector would return on the rendered frames, without rendering: the board
    corners projected from the true pose, those inside the image kept, white noise of
    `corner_sigma_px` per axis added, then the same PnP as pnp.Detector.observe. For statistics
    over many recordings (tests/calib/test_multi_seed.py)."""
    from oibar.calib.pnp import MIN_CORNERS, Observation, pose_covariance

    obj_all = cfg.pattern.corners_pattern_m()
    tau = frame_times(cfg) + cfg.offset_s
    T_tc = T_target_cam_at(tau, cfg)
    rng = np.random.default_rng([cfg.seed, 4000])
    K, dist = intr.K, intr.dist
    out: list[Observation | None] = []  # None: a frame with too few corners in view
    for k in range(cfg.n_frames):
        T_cp = inv_T(T_tc[k]) @ cfg.pattern.T_target_pattern
        rvec = cv2.Rodrigues(T_cp[:3, :3])[0]
        uv = cv2.projectPoints(obj_all.reshape(-1, 1, 3), rvec, T_cp[:3, 3], K, dist)[0].reshape(-1, 2)
        inside = (
            (uv[:, 0] > margin_px)
            & (uv[:, 0] < intr.width_px - 1 - margin_px)
            & (uv[:, 1] > margin_px)
            & (uv[:, 1] < intr.height_px - 1 - margin_px)
        )
        ids = np.flatnonzero(inside)
        if len(ids) < MIN_CORNERS:
            out.append(None)
            continue
        uv = uv[ids] + rng.normal(0.0, corner_sigma_px, (len(ids), 2))
        obj = obj_all[ids]
        ok, rv, tv = cv2.solvePnP(obj, uv, K, dist, flags=cv2.SOLVEPNP_IPPE)
        rv, tv = cv2.solvePnPRefineLM(obj, uv, K, dist, rv, tv)
        T = make_T(cv2.Rodrigues(rv)[0], tv.ravel())
        proj = cv2.projectPoints(obj, rv, tv, K, dist)[0].reshape(-1, 2)
        rms = float(np.sqrt(np.mean(np.sum((proj - uv) ** 2, axis=1))))
        out.append(Observation(ids, uv, T, pose_covariance(T, obj, K, 1.0), rms))
    return out


def simulated_tracks(cfg: SynthConfig) -> tuple:
    """The two mocap tracks of `mocap_samples`, as io.read_mocap_csv would return them."""
    from oibar.calib.timing import Track

    mo = mocap_samples(cfg)
    return Track("housing", mo["t_s"], mo["housing"]), Track("tmarkers", mo["t_s"], mo["tmarkers"])


def truth(cfg: SynthConfig) -> dict:
    def pose(T):
        return {"t_m": T[:3, 3].tolist(), "q_wxyz": R_to_quat_wxyz(T[:3, :3]).tolist()}

    return {
        "T_housing_cam": pose(cfg.T_housing_cam),
        "T_tmarkers_target": pose(cfg.T_tmarkers_target),
        "offset_s": cfg.offset_s,
        "sigma_t_m": cfg.sigma_t_m,
        "sigma_r_deg": cfg.sigma_r_deg,
        "n_frames": cfg.n_frames,
        "frame_rate_hz": cfg.frame_rate_hz,
        "mocap_rate_hz": cfg.mocap_rate_hz,
        "seed": cfg.seed,
    }


def write_recording(out_dir: Path, cfg: SynthConfig | None = None, images: bool = True) -> dict:
    """A complete recording as a user would bring it from the lab, plus truth.json."""
    from oibar.calib.io import write_intrinsics, write_pattern

    cfg = cfg or SynthConfig()
    out_dir = Path(out_dir)
    (out_dir / "frames").mkdir(parents=True, exist_ok=True)
    intr = Intrinsics.oibar_default()
    write_mocap_csv(out_dir / "mocap.csv", mocap_samples(cfg))
    t_f = frame_times(cfg)
    rows = ["frame,file,time_s"] + [f"{k},frames/{k:06d}.png,{t:.6f}" for k, t in enumerate(t_f)]
    (out_dir / "frames.csv").write_text("\n".join(rows) + "\n")
    write_pattern(out_dir / "pattern.json", cfg.pattern)
    write_intrinsics(out_dir / "intrinsics.json", intr)
    tr = truth(cfg)
    (out_dir / "truth.json").write_text(json.dumps(tr, indent=2) + "\n")
    if images:
        render_frames(cfg, intr, out_dir)
    return tr


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m oibar_hil.calib_synth", description=__doc__.splitlines()[0])
    ap.add_argument("out", type=Path)
    ap.add_argument("--poses", type=int, default=200, help="frames in the calibration motion (default 200)")
    ap.add_argument("--seed", type=int, default=1)
    a = ap.parse_args(argv)
    write_recording(a.out, SynthConfig(n_frames=a.poses, seed=a.seed))
    print(f"wrote {a.out} (mocap.csv, frames.csv, frames/, pattern.json, intrinsics.json, truth.json)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
