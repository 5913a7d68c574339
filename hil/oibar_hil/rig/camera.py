"""The HIL rig's rendered camera: what the service vehicle's camera would see for the rig
world's relative pose, rendered so the navigation daemon can run the CNN in the loop.

The frames must come from the distribution the CNN was trained on, so nothing here is new:
the scene, lighting, orbit clock, intrinsics (744x480, f = 583.3 px) and image path are those of
the synthetic dataset (oibar_hil.dataset) for one of the paper's sequence specs:

  pose      (r_D_m, att_rad) of the rig world -> (T_cam_target, R_cam_target) with
            oibar.geometry.docking.camera_pose_from_docking (the mount and probe numbers of
            GEOMETRY, the same ones oibar_hil.relpose labels the dataset with), then the
            camera's pose in LVLH from the spec's port, as relpose.camera_poses does;
  scene     loaded by dataset.load_spec_scene, the generator's own: scene_parts(background, port),
            Perlin seed = the spec's seed and, for a spec with look "randomized", the LookParams
            dataset.spec_look draws (oibar_hil.randomize: materials, lamps, backdrop, exposure,
            vignetting, lens distortion; the renderer keeps each lamp's irradiance at the
            fixture as the camera moves, per frame, as for the data set). A spec drawn by
            Mitsuba (render_mitsuba: the lab look, the matched validation and test looks),
            which the rig does not run, is refused (RigCameraError);
  orbit     rig time t_s = 0 is the dataset's t = 0 for the spec (the moment the Sun has the
            spec's in-plane elevation; both start the approach at 10 m). The orbit clock runs
            with t_s: Sun sampled once per second (dataset.SUN_UPDATE_S, so the shadow map is
            reused for 10 frames at 10 Hz), Earth rotation at t_s, Earth centre fixed at t = 0,
            exactly as dataset.plan_sequence;
  sensor    sensor_effects=True: the spec's blur/noise (zero for the paper's sequences) and the
            dataset's image format round trip (JPEG quality 95, 4:4:4, decoded by PIL as the
            training loader does). sensor_effects=False: the rasteriser's pixels as they are.

The chaser's own end-effector is not drawn, as in the dataset (the camera rides on it).

GL contexts: each call makes this camera's EGL context current and leaves none current
afterwards (moderngl's context manager), so it may be called from any one thread at a time
(e.g. host/oibar/camera's LatestFrame reader thread). Other moderngl code in the same thread
must enter its own context (``with ctx:``) rather than assume it is still current.
"""

from __future__ import annotations

import io
import threading
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from oibar.geometry.camera import PinholeCamera
from oibar.geometry.docking import GEOMETRY, DockingGeometry, camera_pose_from_docking

from ..dataset import (
    PAPER_SEQUENCES,
    SUN_UPDATE_S,
    DatasetError,
    SequenceSpec,
    encode_image,
    load_spec_file,
    load_spec_scene,
)
from ..orbit import DEFAULT_TLE, TargetOrbit, julian_date, parse_utc
from ..ports import PORTS, Port
from ..render import RenderSettings

SCENES = {spec.name: spec for spec in PAPER_SEQUENCES.values()}
DEFAULT_SCENE = "seq01"  # a test sequence of the CNN: the demo runs on a scene it never trained on


class RigCameraError(RuntimeError):
    """The rendered camera cannot be built or used: unknown scene, a look it cannot draw, no GL
    context, closed."""


@dataclass(frozen=True)
class RenderedFrame:
    image: np.ndarray  # (480, 744, 3) uint8 RGB, row 0 at the top
    T_cam_target_m: np.ndarray  # ground-truth label of this frame (dataset convention)
    R_cam_target: np.ndarray
    t_s: float  # rig (mission) time the frame was rendered for
    frame: int  # 0, 1, ... per camera


def scene_spec(scene: str | SequenceSpec) -> SequenceSpec:
    """A paper sequence name (seq01..seq12), ``FILE:NAME`` (scene NAME of a scene-set file such
    as models/scenes/val.json: the closed loop on a validation scene's look, so a choice made
    in the loop need not be made on a test scene's; models/scenes/train_dr.json:dr005, a
    randomised look) or a full SequenceSpec -> a validated spec the rig camera can render."""
    if isinstance(scene, SequenceSpec):
        spec = scene
    elif isinstance(scene, str) and scene in SCENES:
        spec = SCENES[scene]
    elif isinstance(scene, str) and ":" in scene:
        path, name = scene.rsplit(":", 1)
        try:
            found = {s.name: s for s in load_spec_file(Path(path))}
        except DatasetError as exc:
            raise RigCameraError(f"scene {scene!r}: {exc}") from exc
        if name not in found:
            raise RigCameraError(
                f"unknown scene {name!r} in {path} (it has {', '.join(sorted(found)) or 'none'})"
            )
        spec = found[name]
    else:
        raise RigCameraError(
            f"unknown scene {scene!r}: give one of the paper's sequences "
            f"({', '.join(sorted(SCENES))}), FILE:NAME of a scene-set file, or a SequenceSpec"
        )
    try:
        spec.validate()
    except ValueError as exc:
        raise RigCameraError(f"bad scene spec: {exc}") from exc
    if spec.renderer == "mitsuba":  # the lab look, or a matched look the path tracer would draw
        raise RigCameraError(
            f"scene {spec.name!r} is drawn by the Mitsuba path tracer (look {spec.look!r}), which the "
            "rig camera does not run (it rasterises): fly a raster scene, matched or randomized "
            "(e.g. models/scenes/val.json:NAME), or render it open-loop with python -m oibar_hil.dataset --spec FILE"
        )
    return spec


def camera_pose_lvlh(
    T_cam_target_m: np.ndarray, R_cam_target: np.ndarray, port: Port
) -> tuple[np.ndarray, np.ndarray]:
    """Label (F_t seen from the camera) + port -> (R_lvlh_cam, p_lvlh_cam_m), as relpose.camera_poses."""
    R_t_cam = np.asarray(R_cam_target, dtype=float).T
    p_t_cam = -R_t_cam @ np.asarray(T_cam_target_m, dtype=float)
    return port.R_lvlh_t @ R_t_cam, port.p_lvlh_t + port.R_lvlh_t @ p_t_cam


def pose_to_lvlh(r_D_m: np.ndarray, att_rad: np.ndarray, port: Port, geom: DockingGeometry = GEOMETRY):
    """Rig world state (probe tip in D, attitude error) -> (R_lvlh_cam, p_lvlh_cam_m,
    T_cam_target_m, R_cam_target)."""
    r_D_m, att_rad = np.asarray(r_D_m, dtype=float), np.asarray(att_rad, dtype=float)
    if (
        r_D_m.shape != (3,)
        or att_rad.shape != (3,)
        or not (np.all(np.isfinite(r_D_m)) and np.all(np.isfinite(att_rad)))
    ):
        raise RigCameraError(f"pose must be two finite 3-vectors, got r_D_m={r_D_m!r}, att_rad={att_rad!r}")
    T_cam_t, R_cam_t = camera_pose_from_docking(r_D_m, att_rad, geom)
    R_lvlh_cam, p_lvlh_cam = camera_pose_lvlh(T_cam_t, R_cam_t, port)
    return R_lvlh_cam, p_lvlh_cam, T_cam_t, R_cam_t


class OrbitClock:
    """Sun and Earth for rig time t_s, as dataset.plan_sequence computes them for frame time t."""

    def __init__(self, spec: SequenceSpec) -> None:
        self.orbit = TargetOrbit(DEFAULT_TLE)
        start = self.orbit.time_for_sun_elevation(parse_utc(spec.epoch_utc), spec.sun_elevation_deg)
        self.start_utc = start
        self.jd0 = julian_date(start)
        self.earth_center_lvlh_km = self.orbit.state(self.jd0).earth_center_lvlh_km
        self._sun_key: float | None = None
        self._sun_lvlh: np.ndarray = np.zeros(3)  # set on the first at(): no key matches None

    def at(self, t_s: float) -> tuple[np.ndarray, np.ndarray]:
        """(sun_lvlh unit vector, R_ecef_lvlh) at rig time t_s."""
        tq = float(np.floor(t_s / SUN_UPDATE_S + 1e-9) * SUN_UPDATE_S)  # same quantisation as the dataset
        if tq != self._sun_key:
            self._sun_lvlh = self.orbit.state(self.jd0 + tq / 86400.0).sun_lvlh
            self._sun_key = tq
        return self._sun_lvlh, self.orbit.state(self.jd0 + t_s / 86400.0).R_ecef_lvlh


class RigCamera:
    """Renders the service vehicle's camera for the rig world's pose; see the module docstring.

    ``RigCamera(scene="seq01", seed=0, sensor_effects=True)``; ``seed`` seeds the sensor noise
    (frame n uses default_rng([seed, n])), which only matters for specs with noise_sigma_dn > 0.
    Building it loads the scene once (a few seconds for the station); each frame then costs one
    render (plus a shadow-map pass when the Sun sample changes, once per simulated second).
    """

    def __init__(
        self,
        scene: str | SequenceSpec = DEFAULT_SCENE,
        seed: int = 0,
        sensor_effects: bool = True,
        geometry: DockingGeometry = GEOMETRY,
        exposure: float = 1.0,  # RenderSettings.exposure: the sensor's gain (issue 62 disperses it)
    ) -> None:
        self.spec = scene_spec(scene)  # unknown scene: fail before any GL work
        if self.spec.look == "randomized" and float(exposure) != 1.0:
            # a randomised look draws its own exposure, which replaces RenderSettings.exposure
            raise RigCameraError(
                f"scene {self.spec.name!r} has a randomized look, whose own exposure the renderer "
                f"uses: exposure={exposure} would be ignored (leave it at 1.0)"
            )
        self.seed = int(seed)
        self.sensor_effects = bool(sensor_effects)
        self.geometry = geometry
        self.port = PORTS[self.spec.port]
        self.camera = PinholeCamera()
        self.clock = OrbitClock(self.spec)
        self._lock = threading.Lock()
        self._frames = 0
        self._renderer = None
        settings = (
            RenderSettings(
                noise_sigma_dn=self.spec.noise_sigma_dn,
                blur_sigma_px=self.spec.blur_sigma_px,
                exposure=float(exposure),
            )
            if self.sensor_effects
            else RenderSettings(exposure=float(exposure))
        )
        try:
            from ..render import Renderer, create_context

            ctx = create_context()
        except Exception as exc:  # noqa: BLE001 - missing moderngl, EGL or Mesa: one clear error
            raise RigCameraError(f"rendered camera unavailable: {exc}") from exc
        try:
            with ctx:  # leaves the context current nowhere, so any thread may render later
                self._renderer = Renderer(self.camera, settings, ctx=ctx)
                load_spec_scene(self._renderer, self.spec)
        except Exception as exc:
            ctx.release()
            self._renderer = None
            raise RigCameraError(f"could not load scene {self.spec.name}: {exc}") from exc

    # -- info --------------------------------------------------------------------------------
    @property
    def scene(self) -> str:
        return self.spec.name

    @property
    def gl_renderer(self) -> str:
        return self._live().gl_renderer

    @property
    def closed(self) -> bool:
        return self._renderer is None

    def _live(self):
        if self._renderer is None:
            raise RigCameraError("the rendered camera is closed")
        return self._renderer

    # -- frames ------------------------------------------------------------------------------
    def render(self, r_D_m: np.ndarray, att_rad: np.ndarray, t_s: float = 0.0) -> RenderedFrame:
        """The camera frame for probe tip r_D_m (m, frame D) and attitude error att_rad (rotation
        vector, body frame) at rig time t_s, with its ground-truth label."""
        R_lvlh_cam, p_lvlh_cam, T_cam_t, R_cam_t = pose_to_lvlh(r_D_m, att_rad, self.port, self.geometry)
        with self._lock:
            r = self._live()
            sun_lvlh, R_ecef_lvlh = self.clock.at(float(t_s))
            n = self._frames
            self._frames += 1
            rng = (
                np.random.default_rng([self.seed, n])
                if self.sensor_effects and self.spec.noise_sigma_dn > 0
                else None
            )
            img = r.render(
                R_lvlh_cam, p_lvlh_cam, sun_lvlh, R_ecef_lvlh, self.clock.earth_center_lvlh_km, rng=rng
            )
        if self.sensor_effects:
            img = self._through_image_format(img)
        return RenderedFrame(image=img, T_cam_target_m=T_cam_t, R_cam_target=R_cam_t, t_s=float(t_s), frame=n)

    def render_ids(self, r_D_m: np.ndarray, att_rad: np.ndarray) -> np.ndarray:
        """Part ids (oibar_hil.meshes ID_*) per pixel, (480, 744) uint8, 0 = background: the
        label pass of the same pose, for checks and ground-truth masks."""
        R_lvlh_cam, p_lvlh_cam, _, _ = pose_to_lvlh(r_D_m, att_rad, self.port, self.geometry)
        with self._lock:
            r = self._live()
            ids = r.render(R_lvlh_cam, p_lvlh_cam, np.array([0.0, 0.0, -1.0]), mode="id")
        return np.ascontiguousarray(ids[:, :, 0])

    def _through_image_format(self, img: np.ndarray) -> np.ndarray:
        """Encode as the dataset stores frames, decode as the training loader reads them."""
        from PIL import Image

        with Image.open(io.BytesIO(encode_image(img, self.spec))) as im:
            return np.asarray(im.convert("RGB"), dtype=np.uint8)

    # -- lifetime ------------------------------------------------------------------------------
    def close(self) -> None:
        with self._lock:
            if self._renderer is not None:
                self._renderer.release()
                self._renderer = None

    def __enter__(self) -> RigCamera:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __del__(self) -> None:  # best effort: GL contexts are not garbage-collected by moderngl
        try:
            self.close()
        except Exception:  # noqa: BLE001
            pass
