"""A second, independent renderer: Mitsuba 3's path tracer on the same scene description.

It draws what `render.Renderer` draws (the same meshes of `meshes.scene_parts`, the same camera,
the same Sun, Earth and backdrop, the same sensor: exposure, clipping, gamma) by other means:
light transport by Monte Carlo path tracing (shadows, Earth-shine and inter-reflections without
shadow maps or patches), so an estimator that only holds on our rasteriser's look shows it here.
Issue 58 keeps it for validation and test looks: the shipped model never trains on its frames.

Units: our rasteriser's shading is ``albedo x irradiance`` with the Sun's irradiance 1; a
Lambertian surface's radiance is ``albedo x E / pi``, so the Sun here is a directional emitter of
irradiance pi and every pixel comes out on the same scale. The Earth is part of the environment:
an equirectangular map of its radiance as the station sees it (a Lambertian globe lit by the Sun,
the texture of `textures.earth_texture`), which lights the scene the way the real one does. The
rasteriser's constant ambient (0.03) has no counterpart: space has none, and the path tracer's
inter-reflections are what it stood for. The `perlin` backdrop is display-referred and lights
nothing in our rasteriser: here too it is laid behind the rendered image by its alpha, not
traced.

Registration: ``render(..., mode="id")`` gives each pixel's part id from the path tracer's own
ray casts (one ray through each pixel's centre), so a test can hold its silhouettes against the
rasteriser's id pass (they agree but for edge pixels).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from oibar.geometry.camera import PinholeCamera

from .meshes import Part
from .render import (
    DEFAULT_EARTH_CENTER_LVLH_KM,
    EARTH_RADIUS_KM,
    RenderSettings,
    apply_sensor_effects,
    earth_rgba,
)
from .textures import earth_ground, perlin_background, sample_equirect

# "matched": our materials, Sun, Earth and backdrop. "lab": the paper's lab (its experimental
# sequences): the fixture alone, printed in matte grey, lit by one lamp beside the camera, on
# black; the lamp's intensity follows the range squared, as a camera's auto-exposure would.
LOOKS = ("matched", "lab")
LAB_GREY = 0.55  # unpainted grey print, matte
LAB_LAMP_OFFSET_M = (0.15, -0.05, 0.0)  # the lamp beside the camera (camera axes, OpenCV)
LAB_SPOT_DEG = (25.0, 20.0)  # the lamp's cut-off and the start of its fall-off, half-angles
ENV_WIDTH_PX = 2048  # the environment map: 0.18 deg a pixel, the Earth's disc 780 px across


@dataclass(frozen=True)
class MitsubaSettings:
    spp: int = 64  # samples per pixel
    max_depth: int = 4  # path length: direct light and up to two bounces more
    variant: str = "scalar_rgb"  # llvm_ad_rgb is faster but needs LLVM >= 16 (docs/synthetic.md)
    roughness: float = 0.12  # GGX alpha of the specular coat of parts with a specular term


def _mi() -> Any:
    try:
        import mitsuba as mi
    except ImportError as exc:  # one clear line: the validation looks need it, flight never does
        raise RuntimeError(
            "Mitsuba 3 is not installed: `pip install -r requirements/mitsuba.txt` (make setup does)"
        ) from exc
    return mi


def env_directions(width: int) -> np.ndarray:
    """(H, W, 3) unit directions, in the map's own frame, of the pixel centres of Mitsuba's
    latitude-longitude environment map (u = atan2(x, -z) / 2 pi, v = acos(y) / pi)."""
    h = width // 2
    u = (np.arange(width) + 0.5) / width
    v = (np.arange(h) + 0.5) / h
    phi, theta = np.meshgrid(2 * np.pi * u, np.pi * v)
    return np.stack([np.sin(theta) * np.sin(phi), np.cos(theta), -np.sin(theta) * np.cos(phi)], axis=-1)


def earth_radiance_map(
    dirs_lvlh: np.ndarray,
    earth_c_km: np.ndarray,
    R_ecef_lvlh: np.ndarray,
    sun: np.ndarray,
    albedo_rgba: np.ndarray,
) -> np.ndarray:
    """Radiance (on the scale where the Sun's irradiance is pi) of the Earth in each direction:
    its ground colour (clouds white) x cos(Sun on the ground), black off the disc."""
    c = np.asarray(earth_c_km, float)
    d = dirs_lvlh.reshape(-1, 3)
    b = d @ c
    disc = b * b - (c @ c - EARTH_RADIUS_KM**2)
    hit = (disc > 0) & (b > 0)
    t = b - np.sqrt(np.where(hit, disc, 0.0))
    n = (t[:, None] * d - c) / EARTH_RADIUS_KM
    n_ecef = n @ np.asarray(R_ecef_lvlh, float).T  # R_ecef_lvlh @ n, row by row
    ground = earth_ground(sample_equirect(albedo_rgba, n_ecef))
    L = ground * np.maximum(n @ np.asarray(sun, float), 0.0)[:, None]
    L[~hit] = 0.0
    return L.reshape(dirs_lvlh.shape).astype(np.float32)


class MitsubaRenderer:
    """Drop-in for `render.Renderer` where a frame may take seconds: ``load_scene(parts,
    background, focus_lvlh, perlin_seed)`` then ``render(R_lvlh_cam, p_lvlh_cam, sun_lvlh,
    R_ecef_lvlh, earth_center_lvlh_km, mode, rng)`` -> (H, W, 3) uint8. The rasteriser's
    `RenderSettings` give the sensor (exposure, gamma, noise, blur) and the Sun's intensity."""

    def __init__(
        self,
        camera: PinholeCamera | None = None,
        settings: RenderSettings | None = None,
        mitsuba: MitsubaSettings | None = None,
        seed: int = 0,
        look: str = "matched",
    ):
        if look not in LOOKS:
            raise ValueError(f"unknown look {look!r} ({'|'.join(LOOKS)})")
        self.look = look
        self.camera = camera or PinholeCamera()
        self.settings = settings or RenderSettings()
        self.mitsuba = mitsuba or MitsubaSettings()
        self.seed = int(seed)
        self.mi = _mi()
        self.mi.set_variant(self.mitsuba.variant)
        self._shapes: dict[str, Any] = {}
        self._part_ids: list[int] = []
        self.background = "iss"
        self._perlin: np.ndarray | None = None
        self._earth_tex = earth_rgba()
        self._env_dirs = env_directions(ENV_WIDTH_PX)
        self.frames = 0
        # what the data set's manifest records as the renderer (beside the rasteriser's GL_RENDERER)
        self.gl_renderer = (
            f"Mitsuba {self.mi.__version__} {self.mitsuba.variant}, {self.mitsuba.spp} spp, {look} look"
        )

    def load_scene(
        self, parts: list[Part], background: str, focus_lvlh: np.ndarray, perlin_seed: int | None = None
    ) -> None:
        mi = self.mi
        if background not in ("iss", "perlin"):
            raise ValueError(f"unknown background {background!r} (iss|perlin)")
        self._shapes, self._part_ids = {}, []
        for i, p in enumerate(parts):
            v = np.asarray(p.mesh.vertices, np.float32)
            f = np.asarray(p.mesh.faces, np.uint32)
            mesh = mi.Mesh(f"part{i}", vertex_count=len(v), face_count=len(f), has_vertex_normals=False)
            params = mi.traverse(mesh)
            params["vertex_positions"] = v.ravel()
            params["faces"] = f.ravel()
            params.update()
            rgb = [float(x) for x in p.rgb]
            bsdf: dict[str, Any]
            if self.look == "lab":
                bsdf = {"type": "diffuse", "reflectance": {"type": "rgb", "value": [LAB_GREY] * 3}}
            elif p.specular > 0:
                bsdf = {
                    "type": "roughplastic",
                    "distribution": "ggx",
                    "alpha": self.mitsuba.roughness,
                    "diffuse_reflectance": {"type": "rgb", "value": rgb},
                    "specular_reflectance": {"type": "rgb", "value": [float(p.specular)] * 3},
                    "nonlinear": True,
                }
            else:
                bsdf = {"type": "diffuse", "reflectance": {"type": "rgb", "value": rgb}}
            mesh.set_bsdf(mi.load_dict(bsdf))
            self._shapes[f"part{i}"] = mesh
            self._part_ids.append(int(p.part_id))
        self.background = background
        self.focus = np.asarray(focus_lvlh, float)
        if background == "perlin" and perlin_seed is None:
            raise ValueError("the perlin background needs a seed")
        self._perlin = (
            perlin_background(perlin_seed)
            if background == "perlin" and perlin_seed is not None and self.look != "lab"
            else None
        )

    def _sensor(self, R_lvlh_cam: np.ndarray, p_lvlh_cam: np.ndarray, spp: int, rfilter: str) -> Any:
        mi, cam = self.mi, self.camera
        # Mitsuba's camera looks along +z with +y up and +x to the left: OpenCV's axes with x
        # and y turned over
        R = np.asarray(R_lvlh_cam, float) @ np.diag([-1.0, -1.0, 1.0])
        M = np.eye(4)
        M[:3, :3], M[:3, 3] = R, np.asarray(p_lvlh_cam, float)
        W, H = cam.width_px, cam.height_px
        fov_x = float(np.degrees(2 * np.arctan(W / (2 * cam.fx_px))))
        return mi.load_dict(
            {
                "type": "perspective",
                "fov": fov_x,
                "fov_axis": "x",
                # the principal point's offset from the image centre, in image widths / heights
                "principal_point_offset_x": (W / 2 - cam.cx_px) / W,
                "principal_point_offset_y": (H / 2 - cam.cy_px) / H,
                "near_clip": cam.near_m,
                "far_clip": 1e5,
                "to_world": mi.ScalarTransform4f(M.tolist()),
                "sampler": {"type": "independent", "sample_count": spp},
                "film": {
                    "type": "hdrfilm",
                    "width": W,
                    "height": H,
                    "pixel_format": "rgba",
                    "rfilter": {"type": rfilter},
                },
            }
        )

    def _scene(self, sensor: Any, integrator: dict, emitters: dict) -> Any:
        return self.mi.load_dict(
            {"type": "scene", "integrator": integrator, "sensor": sensor, **self._shapes, **emitters}
        )

    def render(
        self,
        R_lvlh_cam: np.ndarray,
        p_lvlh_cam: np.ndarray,
        sun_lvlh: np.ndarray,
        R_ecef_lvlh: np.ndarray | None = None,
        earth_center_lvlh_km: np.ndarray | None = None,
        mode: str = "shaded",
        rng: np.random.Generator | None = None,
        seed: int | None = None,
    ) -> np.ndarray:
        """One frame as (H, W, 3) uint8, row 0 at the top (mode 'id': part ids in channel 0).
        `seed` seeds the path tracer's samples (default: the renderer's seed and a frame count)."""
        if not self._shapes:
            raise RuntimeError("load_scene() first")
        mi, s = self.mi, self.settings
        if mode == "id":
            return self._ids(R_lvlh_cam, p_lvlh_cam)
        sun = np.asarray(sun_lvlh, float)
        sun = sun / np.linalg.norm(sun)
        earth_c = (
            np.array(DEFAULT_EARTH_CENTER_LVLH_KM)
            if earth_center_lvlh_km is None
            else np.asarray(earth_center_lvlh_km, float)
        )
        R_ecef = np.eye(3) if R_ecef_lvlh is None else np.asarray(R_ecef_lvlh, float)
        if self.look == "lab":
            emitters = self._lab_lamp(np.asarray(R_lvlh_cam, float), np.asarray(p_lvlh_cam, float))
        else:
            env = earth_radiance_map(self._env_dirs, earth_c, R_ecef, sun, self._earth_tex) * s.sun_intensity
            emitters = {
                "sun": {
                    "type": "directional",
                    "direction": (-sun).tolist(),  # the direction light travels
                    "irradiance": {"type": "rgb", "value": [np.pi * s.sun_intensity] * 3},
                },
                "earth": {"type": "envmap", "bitmap": mi.Bitmap(env)},
            }
        integrator = {
            "type": "path",
            "max_depth": self.mitsuba.max_depth,
            "hide_emitters": self.background == "perlin" or self.look == "lab",
        }
        sensor = self._sensor(R_lvlh_cam, p_lvlh_cam, self.mitsuba.spp, "gaussian")
        scene = self._scene(sensor, integrator, emitters)
        frame_seed = self.seed * 100003 + self.frames if seed is None else int(seed)
        img = np.asarray(mi.render(scene, seed=frame_seed), np.float32)
        self.frames += 1
        rgb, alpha = img[..., :3], np.clip(img[..., 3:4], 0.0, 1.0)
        out = np.clip(s.exposure * rgb, 0.0, 1.0) ** (1.0 / s.gamma)
        if self._perlin is not None:
            out = out * alpha + self._backdrop(R_lvlh_cam) * (1.0 - alpha)
        img8 = (np.clip(out, 0.0, 1.0) * 255 + 0.5).astype(np.uint8)
        return apply_sensor_effects(img8, s.noise_sigma_dn, s.blur_sigma_px, rng)

    def _lab_lamp(self, R_lvlh_cam: np.ndarray, p_lvlh_cam: np.ndarray) -> dict:
        """One spot lamp beside the camera, aimed at the fixture; its intensity gives the
        fixture's face the Sun's irradiance at whatever range (auto-exposure)."""
        mi = self.mi
        pos = p_lvlh_cam + R_lvlh_cam @ np.asarray(LAB_LAMP_OFFSET_M)
        dist = float(np.linalg.norm(self.focus - pos))
        up = R_lvlh_cam @ np.array([0.0, -1.0, 0.0])
        to_world = mi.ScalarTransform4f().look_at(
            origin=pos.tolist(), target=self.focus.tolist(), up=up.tolist()
        )
        return {
            "lamp": {
                "type": "spot",
                "to_world": to_world,
                "cutoff_angle": LAB_SPOT_DEG[0],
                "beam_width": LAB_SPOT_DEG[1],
                "intensity": {
                    "type": "rgb",
                    "value": [np.pi * dist * dist * self.settings.sun_intensity] * 3,
                },
            }
        }

    def _backdrop(self, R_lvlh_cam: np.ndarray) -> np.ndarray:
        """The perlin backdrop as the rasteriser draws it (fixed in LVLH, display-referred, the
        exposure applied as it does), nearest texel."""
        assert self._perlin is not None
        cam, s = self.camera, self.settings
        u, v = np.meshgrid(np.arange(cam.width_px) + 0.5, np.arange(cam.height_px) + 0.5)
        d = np.stack([(u - cam.cx_px) / cam.fx_px, (v - cam.cy_px) / cam.fy_px, np.ones_like(u)], -1)
        d = d @ np.asarray(R_lvlh_cam, float).T
        d /= np.linalg.norm(d, axis=-1, keepdims=True)
        tex = sample_equirect(self._perlin, d)
        out: np.ndarray = tex / 255.0 * s.exposure ** (1.0 / s.gamma)
        return out

    def _ids(self, R_lvlh_cam: np.ndarray, p_lvlh_cam: np.ndarray) -> np.ndarray:
        """Part ids by one ray through each pixel's centre (Mitsuba's own ray casting: the aov
        integrator's shape index, 0 where the ray meets nothing, else 1 + the shape's place in
        the scene's list)."""
        mi = self.mi
        sensor = self._sensor(R_lvlh_cam, p_lvlh_cam, 1, "box")
        scene = self._scene(sensor, {"type": "aov", "aovs": "si:shape_index"}, {})
        index = np.asarray(mi.render(scene, seed=0), np.float32)[..., -1].round().astype(int)
        names = [sh.id() for sh in scene.shapes()]
        part_of = np.zeros(len(names) + 1, np.uint8)
        for k, name in enumerate(names):
            part_of[k + 1] = self._part_ids[int(name[len("part") :])]
        ids = part_of[np.clip(index, 0, len(names))]
        return np.repeat(ids[..., None], 3, axis=2)
