"""Keypoint geometry of the pose estimator: crop windows at full resolution, and the pose from
2-D keypoints by PnP. Shared by training (oibar_models) and flight (oibar.nav.pose), so both cut
the same pixels and solve the same problem. numpy + OpenCV; no torch.

Pixel convention: continuous coordinates with the origin at the image's top-left corner, pixel
centres at i + 0.5 (docs/synthetic.md). OpenCV's warp and PnP count from pixel centres; the
conversions are done here and nowhere else.

A crop is a square window of side `side_px` (full-resolution pixels) centred at `center_px`,
optionally turned by `angle_rad`, resampled to `out_px` x `out_px`. `A` (2x3) maps a frame
pixel to a crop pixel; keypoints found in the crop map back through its inverse, so the PnP
always runs in the frame's own pixels with the frame's own intrinsics.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from oibar.geometry.camera import project_target_points as project  # target points -> px, corner convention
from oibar.geometry.fixture import FIXTURE_KEYPOINTS  # noqa: F401  (re-exported)
from oibar.geometry.rotations import matrix_to_rotvec, rotvec_to_matrix, skew


@dataclass(frozen=True)
class CropWindow:
    center_px: tuple[float, float]
    side_px: float
    out_px: int
    angle_rad: float = 0.0

    @property
    def scale(self) -> float:
        """Crop pixels per frame pixel."""
        return self.out_px / self.side_px

    def matrix(self) -> np.ndarray:
        """2x3 affine frame px -> crop px (corner convention)."""
        s, c, a = self.scale, np.asarray(self.center_px, float), self.angle_rad
        rot = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]) * s
        t = self.out_px / 2.0 - rot @ c
        return np.hstack([rot, t[:, None]])

    def stepped(self, dx: float, dy: float, k: float) -> CropWindow:
        """The window `dx`, `dy` of this one's sides off its centre (along the frame's axes), `k`
        times its side: one step of the estimator's searches (SEARCH_STEPS, the zoom, the scan's
        shrunk read)."""
        c = (self.center_px[0] + dx * self.side_px, self.center_px[1] + dy * self.side_px)
        return CropWindow(c, self.side_px * k, self.out_px, self.angle_rad)

    def to_crop(self, uv_px: np.ndarray) -> np.ndarray:
        A = self.matrix()
        out: np.ndarray = np.asarray(uv_px, float) @ A[:, :2].T + A[:, 2]
        return out

    def to_frame(self, uv_crop: np.ndarray) -> np.ndarray:
        A = self.matrix()
        out: np.ndarray = (np.asarray(uv_crop, float) - A[:, 2]) @ np.linalg.inv(A[:, :2]).T
        return out


def window_around(
    points_px: np.ndarray, out_px: int, margin: float, min_side_px: float = 24.0, angle_rad: float = 0.0
) -> CropWindow:
    """The square window centred on the points' bounding box, `margin` times its larger side. A
    window turned by `angle_rad` takes the box in its own turned axes, so that it frames the
    points as the crop will show them (a turned fixture's box along the frame's axes is larger)."""
    p = np.asarray(points_px, float)
    if angle_rad == 0.0:
        lo, hi = p.min(0), p.max(0)
        side = max(float(np.max(hi - lo)) * margin, min_side_px)
        return CropWindow(center_px=tuple((lo + hi) / 2.0), side_px=side, out_px=out_px)
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    rot = np.array([[c, -s], [s, c]])  # frame -> crop axes (CropWindow.matrix)
    q = p @ rot.T
    lo, hi = q.min(0), q.max(0)
    side = max(float(np.max(hi - lo)) * margin, min_side_px)
    centre = rot.T @ ((lo + hi) / 2.0)
    return CropWindow(
        center_px=(float(centre[0]), float(centre[1])), side_px=side, out_px=out_px, angle_rad=angle_rad
    )


def image_roll_rad(K: np.ndarray, R_cam_target: np.ndarray, T_cam_target_m: np.ndarray) -> float:
    """How far the fixture is turned in the image: the angle (rad, (-pi, pi]) of the target's +x
    axis, drawn at the target's origin, from the frame's +u axis towards +v. 0 for a fixture seen
    as in training (every training set but train_dr is unrolled); a camera rolled about its
    boresight by a turns it by about a. NaN where the origin projects nowhere."""
    uv = project(K, np.array([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0]]), R_cam_target, T_cam_target_m)
    d = uv[1] - uv[0]
    if not np.all(np.isfinite(d)):
        return float("nan")
    return float(np.arctan2(d[1], d[0]))


def cut(image: np.ndarray, win: CropWindow) -> np.ndarray:
    """The crop (out_px, out_px, 3) uint8. Outside the frame reads black. When the window shrinks
    the image more than 1.5x, the frame is first area-averaged by an integer factor (bilinear
    alone would alias the fine rim edges of a close fixture)."""
    import cv2

    h, w = image.shape[:2]
    A = win.matrix()
    src = image
    f = int(np.floor(1.0 / win.scale)) if win.scale < 1 / 1.5 else 1
    if f > 1:
        ws, hs = max(1, round(w / f)), max(1, round(h / f))
        src = cv2.resize(image, (ws, hs), interpolation=cv2.INTER_AREA)
        # corner convention: a resize by (ws/w, hs/h) scales coordinates exactly
        A = A @ np.array([[w / ws, 0, 0], [0, h / hs, 0], [0, 0, 1.0]])
    # corner -> centre convention on both sides: q_c = A p_c  <=>  q_n = A p_n + (A[:, :2] @ 0.5 - 0.5)
    M = A.copy()
    M[:, 2] += A[:, :2] @ np.array([0.5, 0.5]) - 0.5
    return cv2.warpAffine(
        src,
        M,
        (win.out_px, win.out_px),
        flags=cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=(0, 0, 0),
    )


def _boresight_to_window(win: CropWindow, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(rotation vector, camera frame, rad, that turns the camera's boresight onto the window
    centre; the window's roll about the crop's boresight)."""
    c = np.linalg.solve(np.asarray(K, float), np.array([*win.center_px, 1.0]))
    d = c / np.linalg.norm(c)
    z = np.array([0.0, 0.0, 1.0])
    axis = np.cross(z, d)
    s = float(np.linalg.norm(axis))
    rv = np.zeros(3) if s < 1e-12 else axis / s * np.arctan2(s, float(d @ z))
    ca, sa = np.cos(win.angle_rad), np.sin(win.angle_rad)
    roll = np.array([[ca, -sa, 0.0], [sa, ca, 0.0], [0.0, 0.0, 1.0]])
    return rv, roll


def R_crop_cam(win: CropWindow, K: np.ndarray) -> np.ndarray:
    """The crop's own camera: boresight through the window centre, x and y turned with the
    window. Maps camera vectors into it. Why: a crop shows the fixture as a camera pointed at it
    would, so an attitude read from the crop is relative to that camera (allocentric), not to
    the real one. Rotating image coordinates by the window's angle is rolling that camera about
    its boresight by the same angle."""
    rv, roll = _boresight_to_window(win, K)
    out: np.ndarray = roll @ rotvec_to_matrix(rv).T  # rotvec_to_matrix(rv): cam <- virtual
    return out


def bearing_in_crop_deg(win: CropWindow, K: np.ndarray) -> np.ndarray:
    """The window's bearing: the rotation (vector, deg) that turns the camera's boresight onto
    the window centre, in the crop's frame. Its x and y are how far off the image centre the
    crop was cut, which the affine crop shows as a keystone (HeadCropGainModel)."""
    rv, roll = _boresight_to_window(win, K)
    out: np.ndarray = np.degrees(roll @ rv)
    return out


def attitude_in_crop_deg(
    win: CropWindow, K: np.ndarray, R_cam_target: np.ndarray, R_ref: np.ndarray
) -> np.ndarray:
    """The attitude head's label: rotation vector (deg) of R_crop_target R_ref^T."""
    R = R_crop_cam(win, K) @ np.asarray(R_cam_target, float) @ np.asarray(R_ref, float).T
    out: np.ndarray = np.degrees(matrix_to_rotvec(R))
    return out


def attitude_from_crop(win: CropWindow, K: np.ndarray, att_deg: np.ndarray, R_ref: np.ndarray) -> np.ndarray:
    """Inverse of attitude_in_crop_deg: the head's output -> R_cam_target."""
    R_crop_target = rotvec_to_matrix(np.radians(np.asarray(att_deg, float))) @ np.asarray(R_ref, float)
    out: np.ndarray = R_crop_cam(win, K).T @ R_crop_target
    return out


@dataclass
class PnpResult:
    ok: bool
    R_cam_target: np.ndarray | None = None
    T_cam_target_m: np.ndarray | None = None
    inliers: np.ndarray | None = None  # indices into the points given
    rms_px: float = float("nan")  # reprojection RMS over the inliers, frame pixels
    reason: str = ""
    # a fit that leaned on an attitude prior: the same keypoints' PnP alone (None when it failed)
    no_prior: PnpResult | None = None

    def pose(self) -> tuple[np.ndarray, np.ndarray]:
        """(R_cam_target, T_cam_target_m) of a successful solve; ValueError otherwise."""
        if not self.ok or self.R_cam_target is None or self.T_cam_target_m is None:
            raise ValueError(f"no pose: {self.reason or 'not solved'}")
        return self.R_cam_target, self.T_cam_target_m


def solve_pnp(
    uv_px: np.ndarray,
    points_m: np.ndarray,
    K: np.ndarray,
    reproj_px: float,
    R_guess: np.ndarray | None = None,
    T_guess: np.ndarray | None = None,
    min_points: int = 5,
) -> PnpResult:
    """Pose of the target from its keypoints: RANSAC (SQPnP on minimal sets) against outliers, then
    Levenberg-Marquardt refinement on the inliers. `reproj_px` is the inlier threshold in frame
    pixels (the caller scales it with the crop: a keypoint's error grows with the window)."""
    import cv2

    uv = np.asarray(uv_px, np.float64)
    P = np.asarray(points_m, np.float64)
    good = np.all(np.isfinite(uv), axis=1)
    if good.sum() < min_points:
        return PnpResult(False, reason=f"only {int(good.sum())} keypoints (need {min_points})")
    idx = np.flatnonzero(good)
    Kc = np.asarray(K, np.float64).copy()
    Kc[0, 2] -= 0.5  # OpenCV counts from pixel centres
    Kc[1, 2] -= 0.5
    uvc = uv[idx] - 0.5
    dist = np.zeros(4)
    try:
        ok, rvec, tvec, inl = cv2.solvePnPRansac(
            P[idx],
            uvc,
            Kc,
            dist,
            iterationsCount=100,
            reprojectionError=float(reproj_px),
            confidence=0.999,
            flags=cv2.SOLVEPNP_SQPNP,
        )
    except cv2.error as exc:
        return PnpResult(False, reason=f"PnP failed ({exc.err})")
    if not ok or inl is None or len(inl) < min_points:
        return PnpResult(False, reason=f"no consistent pose ({0 if inl is None else len(inl)} inliers)")
    inl = inl.ravel()
    R, T = refine_reprojection(
        uv[idx][inl], P[idx][inl], np.asarray(K, np.float64), cv2.Rodrigues(rvec)[0], tvec.ravel()
    )
    if T[2] <= 0:
        return PnpResult(False, reason="pose behind the camera")
    res = project(K, P[idx][inl], R, T) - uv[idx][inl]
    rms = float(np.sqrt(np.mean(np.sum(res**2, axis=1))))
    return PnpResult(True, R, T, idx[inl], rms)


def refine_reprojection(
    uv_px: np.ndarray, points_m: np.ndarray, K: np.ndarray, R: np.ndarray, T: np.ndarray, iterations: int = 20
) -> tuple[np.ndarray, np.ndarray]:
    """The pose minimising the keypoints' squared reprojection error, from a start near it (RANSAC's):
    Levenberg-Marquardt on the closed-form Jacobian (_reprojection_jacobian). The damping keeps a
    far frame's nearly flat tilt from taking a long step into the mirrored pose. The same minimum
    as OpenCV's solvePnPRefineLM, which took 1.3-1.6 ms for 14 points here (0.3 ms an iteration,
    4-5 to converge): the largest single cost of a tracked frame's fit."""
    R = np.asarray(R, float)
    T = np.asarray(T, float)
    sig = np.ones((len(uv_px), 1))
    r0, J = _reprojection_jacobian(K, points_m, uv_px, sig, R, T)
    if not np.all(np.isfinite(r0)) or not np.all(np.isfinite(J)):
        return R, T
    cost = float(r0 @ r0)
    lam = 1e-3
    for _ in range(iterations):
        A = J.T @ J
        g = J.T @ r0
        try:
            step = -np.linalg.solve(A + lam * np.diag(np.diag(A)), g)
        except np.linalg.LinAlgError:
            break
        R1 = rotvec_to_matrix(step[:3]) @ R
        T1 = T + step[3:]
        r1, J1 = _reprojection_jacobian(K, points_m, uv_px, sig, R1, T1)
        cost1 = float(r1 @ r1)
        if np.isfinite(cost1) and cost1 <= cost and np.all(np.isfinite(J1)):
            R, T, r0, J = R1, T1, r1, J1
            # converged: the cost no longer falls (relative 1e-10) or the step is below 1e-10
            done = cost - cost1 <= 1e-10 * cost or (
                np.linalg.norm(step[:3]) < 1e-10
                and np.linalg.norm(step[3:]) < 1e-10 * max(1.0, float(np.linalg.norm(T)))
            )
            cost = cost1
            lam = max(lam / 10.0, 1e-9)
            if done:
                break
        else:
            lam *= 10.0
            if lam > 1e6:
                break
    return R, T


def _so3_log_jacobian_inv(phi: np.ndarray) -> np.ndarray:
    """d log(exp(d) A) / d d at d = 0, where phi = log(A): the inverse of SO(3)'s left Jacobian,
    I - [phi]x / 2 + (1 / t^2 - (1 + cos t) / (2 t sin t)) [phi]x^2 with t = |phi|."""
    t = float(np.linalg.norm(phi))
    S = skew(phi)
    # the series 1/12 + t^2/720 below 1e-4 rad, where the closed form loses its digits
    c = 1.0 / 12.0 + t * t / 720.0 if t < 1e-4 else 1.0 / t**2 - (1.0 + np.cos(t)) / (2.0 * t * np.sin(t))
    out: np.ndarray = np.eye(3) - 0.5 * S + c * (S @ S)
    return out


def _reprojection_jacobian(
    K: np.ndarray, P: np.ndarray, uv: np.ndarray, sig: np.ndarray, R: np.ndarray, T: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The keypoints' reprojection residuals ((u, v) per point, over sig) at (R, T) and their
    Jacobian (2N, 6) for the step R <- exp(d_rot) R, T <- T + d_T, in closed form."""
    q = P @ R.T  # points turned into the camera's axes, before the translation
    p = q + T
    w = p @ K[2]  # the homogeneous scale (z for a pinhole K)
    uvw = p @ K.T
    with np.errstate(divide="ignore", invalid="ignore"):
        proj = uvw[:, :2] / w[:, None]
        proj[w <= 0] = np.nan
        # d(u, v)/dp, (N, 2, 3): (K's rows 0-1 - (u, v) K's row 2) / w
        dproj_dp = (K[None, :2, :] - proj[:, :, None] * K[None, None, 2, :]) / w[:, None, None]
    dproj_dp = dproj_dp / sig[:, :, None]
    # dp/d d_rot = -[q]x (exp(d) q = q + d x q), so each row a of d(u, v)/dp gives -a [q]x = q x a
    # (written out: numpy's cross costs twice as much here); dp/d d_T = I
    qx, qy, qz = q[:, None, 0], q[:, None, 1], q[:, None, 2]
    ax, ay, az = dproj_dp[..., 0], dproj_dp[..., 1], dproj_dp[..., 2]
    d_rot = np.stack([qy * az - qz * ay, qz * ax - qx * az, qx * ay - qy * ax], axis=-1)
    J_img = np.concatenate([d_rot, dproj_dp], axis=2).reshape(-1, 6)
    return ((proj - uv) / sig).ravel(), J_img


def _prior_fit_jacobian(
    K: np.ndarray,
    P: np.ndarray,
    uv: np.ndarray,
    sig: np.ndarray,
    R: np.ndarray,
    T: np.ndarray,
    R_prior: np.ndarray,
    sigma_prior_rad: float,
) -> tuple[np.ndarray, np.ndarray]:
    """refine_with_prior's residuals at (R, T) and their Jacobian in closed form, for the step
    R <- exp(d_rot) R, T <- T + d_T: reprojection (u, v per point, over sig), then
    log(R R_prior^T) over sigma_prior. Closed form because this is the navigator's hottest loop:
    central differences cost 13 residual evaluations per step (42 % of a tracked frame)."""
    r_img, J_img = _reprojection_jacobian(K, P, uv, sig, R, T)
    phi = matrix_to_rotvec(R @ R_prior.T)
    J_att = np.zeros((3, 6))
    J_att[:, :3] = _so3_log_jacobian_inv(phi) / sigma_prior_rad
    r = np.concatenate([r_img, phi / sigma_prior_rad])
    return r, np.concatenate([J_img, J_att])


def refine_with_prior(
    uv_px: np.ndarray,
    points_m: np.ndarray,
    K: np.ndarray,
    R: np.ndarray,
    T: np.ndarray,
    R_prior: np.ndarray,
    sigma_px: float | np.ndarray,
    sigma_prior_rad: float,
    iterations: int = 8,
) -> tuple[np.ndarray, np.ndarray, float, float]:
    """The pose that best explains the keypoints *and* an independent attitude estimate (the
    direct model's): Gauss-Newton on  sum |reprojection / sigma_px|^2 + |log(R R_prior^T) / sigma_prior|^2.

    Why: the fixture is nearly planar and small. At 10 m a 1 deg tilt moves its keypoints by a
    hundredth of a pixel, so PnP's attitude there is noise while its position is sharp; close in,
    the keypoints pin the attitude far better than the direct model. Weighting both by their
    errors lets each dominate where it is good, with no range switch to tune.
    `sigma_px` is one number or one per point (keypoints are not all found equally well).
    Returns (R, T, rms_px over the given points, cost)."""
    uv = np.asarray(uv_px, float)
    good = np.all(np.isfinite(uv), axis=1)
    sig = np.broadcast_to(np.asarray(sigma_px, float), (len(uv),))[good][:, None]
    P, uv = np.asarray(points_m, float)[good], uv[good]
    R = np.asarray(R, float)
    T = np.asarray(T, float)
    Km = np.asarray(K, float)
    for _ in range(iterations):
        r0, J = _prior_fit_jacobian(Km, P, uv, sig, R, T, R_prior, sigma_prior_rad)
        if not np.all(np.isfinite(r0)) or not np.all(np.isfinite(J)):
            break
        try:
            step = -np.linalg.solve(J.T @ J + 1e-9 * np.eye(6), J.T @ r0)
        except np.linalg.LinAlgError:
            break
        R = rotvec_to_matrix(step[:3]) @ R
        T = T + step[3:]
        if np.linalg.norm(step[:3]) < 1e-9 and np.linalg.norm(step[3:]) < 1e-9 * max(
            1.0, float(np.linalg.norm(T))
        ):
            break
    res = project(K, P, R, T) - uv
    rms = float(np.sqrt(np.mean(np.sum(res**2, axis=1))))
    cost = float(np.sum((res / sig) ** 2) + np.sum(matrix_to_rotvec(R @ R_prior.T) ** 2) / sigma_prior_rad**2)
    return R, T, rms, cost


def translation_given_rotation(
    uv_px: np.ndarray, points_m: np.ndarray, K: np.ndarray, R: np.ndarray
) -> np.ndarray | None:
    """Least-squares T for a known R: each keypoint gives two equations linear in T
    ((u - cx) / fx * z - x = 0, the same for v), so this has no local minima and no flips."""
    uv = np.asarray(uv_px, float)
    good = np.all(np.isfinite(uv), axis=1)
    if good.sum() < 2:
        return None
    q = np.asarray(points_m, float)[good] @ np.asarray(R, float).T
    a = (uv[good, 0] - K[0, 2]) / K[0, 0]
    b = (uv[good, 1] - K[1, 2]) / K[1, 1]
    A = np.concatenate(
        [
            np.stack([-np.ones_like(a), np.zeros_like(a), a], 1),
            np.stack([np.zeros_like(b), -np.ones_like(b), b], 1),
        ]
    )
    rhs = np.concatenate([q[:, 0] - a * q[:, 2], q[:, 1] - b * q[:, 2]])
    T = np.linalg.lstsq(A, rhs, rcond=None)[0]
    return T if T[2] > 0 else None


def map_pose(
    uv_px: np.ndarray,
    points_m: np.ndarray,
    K: np.ndarray,
    reproj_px: float,
    R_prior: np.ndarray,
    sigma_px: float | np.ndarray | None,
    sigma_prior_rad: float | None,
    min_points: int = 5,
    pnp: PnpResult | None = None,
) -> PnpResult:
    """The pose from keypoints and an attitude prior. Two starts, refined by refine_with_prior, the
    lower cost kept: PnP (RANSAC + LM) and (R_prior, its least-squares T). The second start is what
    saves far frames, where near-planar keypoints let PnP fall into a mirrored pose that fits the
    pixels as well as the true one. Keypoints further than `reproj_px` from the chosen pose are
    dropped and the pose refined again. Without a prior (sigma None): PnP alone. `sigma_px`: one
    number, or one per keypoint (the export's error model, KeypointErrorModel). A fit with the
    prior carries the PnP-alone one as `no_prior` (what a filter should fuse: see PoseEstimate).
    `pnp`: that PnP-alone fit of these keypoints, when the caller has made it already."""
    if pnp is None:
        pnp = solve_pnp(uv_px, points_m, K, reproj_px, min_points=min_points)
    if sigma_px is None or sigma_prior_rad is None:
        return pnp
    uv = np.asarray(uv_px, float)
    starts: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
    if pnp.ok and pnp.R_cam_target is not None and pnp.T_cam_target_m is not None:
        used = np.full_like(uv, np.nan)
        used[pnp.inliers] = uv[pnp.inliers]
        starts.append((pnp.R_cam_target, pnp.T_cam_target_m, used))
    T0 = translation_given_rotation(uv, points_m, K, R_prior)
    if T0 is not None:
        starts.append((np.asarray(R_prior, float), T0, uv))
    best: tuple[float, PnpResult] | None = None
    for R0, T0, uv0 in starts:
        if np.sum(np.all(np.isfinite(uv0), axis=1)) < min_points:
            continue
        R, T, _, _ = refine_with_prior(uv0, points_m, K, R0, T0, R_prior, sigma_px, sigma_prior_rad)
        err = np.linalg.norm(project(K, points_m, R, T) - uv, axis=1)
        keep = np.isfinite(err) & (err < reproj_px)
        if keep.sum() < min_points:
            continue
        uv1 = np.where(keep[:, None], uv, np.nan)
        R, T, rms, cost = refine_with_prior(uv1, points_m, K, R, T, R_prior, sigma_px, sigma_prior_rad)
        dropped = ~keep & np.all(np.isfinite(uv), axis=1)
        cost += float(
            np.sum((reproj_px / np.broadcast_to(np.asarray(sigma_px, float), (len(uv),))[dropped]) ** 2)
        )
        if T[2] > 0 and (best is None or cost < best[0]):
            best = (cost, PnpResult(True, R, T, np.flatnonzero(keep), rms))
    if best is None:
        return PnpResult(False, reason=pnp.reason or "no consistent pose with the attitude prior")
    best[1].no_prior = pnp if pnp.ok else None
    return best[1]


MIRROR_ATT = np.array([1.0, -1.0, -1.0])
"""A rotation vector seen in a left-right mirrored image of a left-right symmetric target:
a reflection keeps the axial x component and turns y and z over."""


def mirror_permutation(points_m: np.ndarray, tol_m: float = 1e-6) -> np.ndarray | None:
    """For a left-right symmetric point set (each point has a twin at -x, same y and z): the index
    of each point's twin (a point on the axis is its own). None when a point has no twin: a
    mirrored image would then show a different target."""
    P = np.asarray(points_m, float)
    twin = np.empty(len(P), int)
    for i, (x, y, z) in enumerate(P):
        d = np.linalg.norm(P - np.array([-x, y, z]), axis=1)
        j = int(np.argmin(d))
        if d[j] > tol_m:
            return None
        twin[i] = j
    return twin


MIRROR_X = np.diag([-1.0, 1.0, 1.0])  # a left-right reflection of the camera's (and the fixture's) x


def mirror_symmetric_attitude(R: np.ndarray) -> bool:
    """Whether an attitude looks the same in a left-right mirror image (M R M = R). The attitude
    head reads R_crop_target R_ref^T; its mirror reading maps back by MIRROR_ATT only when R_ref
    is such an attitude (identity, every export so far)."""
    return bool(np.allclose(MIRROR_X @ np.asarray(R, float) @ MIRROR_X, R, atol=1e-6))


def mirror_crop_px(kp_crop_px: np.ndarray, twin: np.ndarray, out_px: int) -> np.ndarray:
    """Keypoints (K, 2) read in (or labelled for) a crop, as they lie in its left-right mirror
    image: each keypoint takes its twin's place (mirror_permutation), u -> out_px - u (corner
    convention). Its own inverse."""
    m: np.ndarray = np.array(kp_crop_px, float)[twin]
    m[:, 0] = out_px - m[:, 0]
    return m


# A corner whose window is flatter than this (grey-level standard deviation, DN) has nothing for
# the sub-pixel search to lock on: a corner in deep shadow, or one off the frame.
CORNER_MIN_CONTRAST_DN = 8.0


def refine_corners_px(
    gray: np.ndarray, uv_px: np.ndarray, idx: np.ndarray, half_win_px: int, max_move_px: float
) -> tuple[np.ndarray, np.ndarray]:
    """Sharp corners (keypoints `idx` of `uv_px`, frame pixels, corner convention) moved onto the
    grey image's own corner to a fraction of a pixel (OpenCV's cornerSubPix: the point where the
    window's gradients are orthogonal to the lines from it). Why: the keypoint network reads a
    crop scaled down to 128 px, so close in it sees the fixture's corners 2-5x coarser than the
    frame has them and reads the fixture's perspective timidly (a turn at 0.5 m at 0.8 of the
    truth). A corner is kept where it was when its window lies partly off the frame, is flat
    (CORNER_MIN_CONTRAST_DN), or when the search moves it more than `max_move_px` (it found
    another corner). Returns (the keypoints with the moved corners, which of `idx` moved)."""
    import cv2

    g = np.asarray(gray, np.float32)
    h, w = g.shape[:2]
    uv = np.array(uv_px, float)
    idx = np.asarray(idx, int)
    moved = np.zeros(len(idx), bool)
    r = int(half_win_px)
    if r < 1 or len(idx) == 0:
        return uv, moved
    cand = []
    for n, j in enumerate(idx):
        u, v = uv[j]
        if not (np.isfinite(u) and np.isfinite(v)):
            continue
        # OpenCV counts from pixel centres; the window and one pixel of gradient must lie inside
        x, y = u - 0.5, v - 0.5
        if not (r + 1 <= x < w - r - 2 and r + 1 <= y < h - r - 2):
            continue
        xi, yi = int(round(x)), int(round(y))
        if float(g[yi - r : yi + r + 1, xi - r : xi + r + 1].std()) < CORNER_MIN_CONTRAST_DN:
            continue
        cand.append((n, j, x, y))
    if not cand:
        return uv, moved
    pts = np.array([[x, y] for _, _, x, y in cand], np.float32).reshape(-1, 1, 2)
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 40, 0.001)
    out = cv2.cornerSubPix(g, pts, (r, r), (-1, -1), crit).reshape(-1, 2).astype(float) + 0.5
    for (n, j, _, _), p in zip(cand, out, strict=True):
        if np.all(np.isfinite(p)) and float(np.linalg.norm(p - uv[j])) <= max_move_px:
            uv[j] = p
            moved[n] = True
    return uv, moved
