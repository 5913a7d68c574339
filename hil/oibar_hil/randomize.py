"""Domain randomisation, the scene-level part (issue 58, part 3): what our rasteriser can draw
differently from one training sequence to the next, each axis a documented distribution drawn
from one seed.

The estimator trained on one look (our painted fixture under the Sun and the Earth, before a
station or a Perlin backdrop) failed on a lab's (matte grey print, one lamp beside the camera,
black). The image-space axes (white balance, exposure and colour jitter, gamma, glare, occlusion,
motion blur, defocus, noise, JPEG) are drawn per crop by `oibar_models.domain`; the axes here need
the scene: materials, lights, backgrounds, and the two optical ones that depend on where a pixel
lies in the whole frame (vignetting, lens distortion). A sequence spec with
`"look": "randomized"` draws one `LookParams` per sequence: `look_for(seed)`, seeded by the spec's
`look_seed` (or its trajectory seed), the same on any machine.

Each axis, its values (probability) and ranges; a range is drawn uniformly unless said:

- material scheme: one material for the whole fixture (0.35: a printed or painted mock-up) or
  one per part (0.65); the kind: painted 0.25, matte grey print 0.2, bare aluminium 0.15,
  anodised aluminium 0.15, MLI foil 0.1, as built 0.15.
- painted: any hue, saturation 0-0.5, value 0.08-0.9; specular 0.05-0.4, shininess 8-64;
  grain 0-0.06.
- matte grey print: grey 0.42-0.68 (tint +-0.02); specular 0-0.06, shininess 4-16; banding
  (layers, streaks) 0.02-0.08 of period 1-4 mm; grain 0.02-0.08.
- bare aluminium: grey 0.55-0.78 (tint +-0.03); specular 0.5-0.9, shininess 40-250; brushed:
  grain 0.03-0.12 stretched 10-40x along X_t.
- anodised aluminium: black (value 0.06-0.15), blue, red, gold or clear (value 0.25-0.6);
  specular 0.2-0.5, shininess 24-96; grain 0-0.05.
- MLI foil: kapton gold (0.6) or silver; specular 0.6-1.0, shininess 80-400; crinkle (a bumped
  normal) 0.15-0.5; grain 0.05-0.2.
- as built: the part's own colour and specular (meshes.py), shininess 48, no texture.
- texture: a periodic 3-D fBm volume seeded by the look, fixed to the fixture, 8-60 cycles a
  metre (1.7-12 cm features); MLI 15-50.
- lighting: Sun and Earth-shine 0.2, Sun only 0.15, Earth-shine only 0.1, one lamp at the
  camera 0.2, one lamp off the camera 0.15, several lamps (2-3, each at or off the camera)
  0.2. Sun x 0.7-1.3; Earth-shine x 0.6-1.6 beside the Sun, x 2.5-5 alone.
- a lamp at the camera: within 0.2 m of the lens in the image plane (the lab's: 0.15 m).
  Off the camera (0.5 each): riding on the camera 0.3-1.5 m aside (-0.3-0.3 m along its axis),
  or fixed in the fixture's frame 1-4 m away, 10-70 deg off its axis on the camera's side.
- every lamp: aimed at the fixture's centre +-5 cm; irradiance there 0.5-1.4 x the Sun's, kept
  as the camera moves (auto-exposure, as Mitsuba's lab look); a cone of half-angle 12-45 deg
  with a soft edge 20-60 % of it; a tint from a warm halogen's to a cool LED's; its own shadow
  (a perspective shadow map, 1024^2).
- ambient: 0-0.05 under the Sun or the Earth, 0-0.2 under lamps.
- backdrop: black 0.3, the Earth and space 0.2, stars 0.15, lab clutter 0.2, Perlin 0.15; stars,
  clutter and Perlin x 0.3-1.0 in brightness.
- exposure: log-uniform 0.6-1.6 (gamma stays 2.2: the crop-level RandomGamma draws it).
- vignetting: none (0.4), else a gain 1 - v (r / r_corner)^2 on the linear signal, v 0-0.45.
- lens distortion: none (0.4), else a radial k1 that moves the image's corner 0.2-1.0 px,
  in or out (k2 = p1 = p2 = 0).

Lens distortion is kept to a calibration's residual: the navigation undistorts its camera's
frames into the canonical pinhole camera (`oibar.camera.calibration.CanonicalRemap`) and the
labels are pinhole projections, so a larger distortion would be label error, not a look. 1 px at
the corner is 0.13 px at a quarter of the diagonal. Geometry is never drawn: every axis changes
pixels' values, never the fixture's silhouette (the label pass is the same for every look), but
for the distortion's residual.
"""

from __future__ import annotations

import colorsys
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from oibar.geometry.camera import PinholeCamera

# The fixture's parts that carry a drawn material (meshes.berthing_fixture's names). The bore at
# the funnel's bottom keeps its dark material in every look: it stands for an unlit 5 cm hole.
FIXTURE_PARTS = ("rim", "plate", "pin_guides", "drogue", "couplings", "connector")
MATERIAL_KINDS = ("painted", "print_grey", "aluminium_bare", "aluminium_anodised", "mli", "as_built")
LIGHTINGS = ("sun_earth", "sun", "earth", "lamp_at_camera", "lamp_off_camera", "lamps")
BACKDROPS = ("black", "earth", "stars", "clutter", "perlin")
MAX_LAMPS = 3
# Part of a randomised sequence's identity (spec.json): what a seed draws changes with the table
# or the renderer's reading of it, so raise this with either, and resume refuses old folders.
LOOK_VERSION = 1
# SeedSequence tag: the look's stream differs from the trajectory's, which is seeded by the same
# spec seed (numpy.random.default_rng(seed) would give both the same numbers).
LOOK_STREAM = 58

_CAM = PinholeCamera()
F_PX = float(_CAM.fx_px)  # the canonical camera's focal length, pixels
CORNER_RADIUS_PX = float(np.hypot(_CAM.cx_px, _CAM.cy_px))  # its principal point to its corner


@dataclass(frozen=True)
class Material:
    """A surface: albedo, Blinn-Phong specular, and a procedural texture (fBm grain on the
    albedo, a bump on the normal, banding)."""

    kind: str
    rgb: tuple[float, float, float]  # diffuse albedo, linear
    specular: float  # specular weight (its peak, Sun = 1)
    shininess: float  # Blinn-Phong exponent: 4 rough .. 400 near mirror
    grain: float  # albedo x (1 +- grain) from the fBm
    bump: float  # normal perturbation (MLI crinkle)
    banding: float  # albedo x (1 +- banding) in layers along Y_t (print layers, paint streaks)
    band_period_m: float
    scale_per_m: float  # the fBm's cycles per metre
    stretch: float  # the fBm stretched along X_t (brushed metal); 1 = isotropic


@dataclass(frozen=True)
class Lamp:
    """A spot lamp. `mount` "camera": rides with the camera, `position_m` in the camera's axes
    (OpenCV); "world": fixed, `position_m` in the fixture's frame F_t. Aimed at the F_t point
    `aim_m`; its irradiance there (Sun = 1) is `irradiance` whatever the distance."""

    mount: str
    position_m: tuple[float, float, float]
    aim_m: tuple[float, float, float]
    irradiance: float
    rgb: tuple[float, float, float]  # tint, max channel 1
    cone_deg: float  # half-angle of the cut-off
    soft_deg: float  # the fall-off's width inside it


@dataclass(frozen=True)
class LookParams:
    seed: int
    scheme: str  # uniform | per_part
    materials: tuple[tuple[str, Material], ...]  # FIXTURE_PARTS name -> material
    lighting: str
    sun_scale: float  # x the Sun's irradiance (0: no Sun)
    earth_scale: float  # x the Earth-shine (0: none)
    ambient: float
    lamps: tuple[Lamp, ...]
    backdrop: str
    backdrop_seed: int
    backdrop_gain: float
    exposure: float
    vignetting: float  # gain 1 - v (r / r_corner)^2
    distortion_k1: float  # OpenCV radial k1 (k2 = p1 = p2 = 0) of the canonical camera

    def material(self, name: str) -> Material | None:
        return dict(self.materials).get(name)

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


@dataclass(frozen=True)
class LookDistribution:
    """The probabilities and ranges of the module's table, in one place; `draw` reads nothing else."""

    p_uniform_scheme: float = 0.35
    p_kind: tuple[float, ...] = (0.25, 0.2, 0.15, 0.15, 0.1, 0.15)  # MATERIAL_KINDS order
    p_lighting: tuple[float, ...] = (0.2, 0.15, 0.1, 0.2, 0.15, 0.2)  # LIGHTINGS order
    sun_scale: tuple[float, float] = (0.7, 1.3)
    earth_scale: tuple[float, float] = (0.6, 1.6)
    earth_alone_scale: tuple[float, float] = (2.5, 5.0)
    lamp_irradiance: tuple[float, float] = (0.5, 1.4)
    lamp_at_camera_m: float = 0.2
    lamp_off_camera_m: tuple[float, float] = (0.3, 1.5)
    lamp_world_m: tuple[float, float] = (1.0, 4.0)
    lamp_world_off_axis_deg: tuple[float, float] = (10.0, 70.0)
    lamp_aim_m: float = 0.05
    lamp_cone_deg: tuple[float, float] = (12.0, 45.0)
    lamp_soft: tuple[float, float] = (0.2, 0.6)
    ambient_space: tuple[float, float] = (0.0, 0.05)
    ambient_lamps: tuple[float, float] = (0.0, 0.2)
    p_backdrop: tuple[float, ...] = (0.3, 0.2, 0.15, 0.2, 0.15)  # BACKDROPS order
    backdrop_gain: tuple[float, float] = (0.3, 1.0)
    exposure: tuple[float, float] = (0.6, 1.6)  # log-uniform
    p_vignetting: float = 0.6
    vignetting: tuple[float, float] = (0.0, 0.45)
    p_distortion: float = 0.6
    distortion_corner_px: tuple[float, float] = (0.2, 1.0)


DEFAULT = LookDistribution()


def _u(rng: np.random.Generator, lo_hi: tuple[float, float]) -> float:
    return float(rng.uniform(*lo_hi))


def _r(x: float, n: int = 4) -> float:
    return float(round(x, n))


def _rgb(*c: float) -> tuple[float, float, float]:
    return (_r(c[0]), _r(c[1]), _r(c[2]))


def _grey(rng: np.random.Generator, lo: float, hi: float, tint: float) -> tuple[float, float, float]:
    g = rng.uniform(lo, hi)
    t = rng.uniform(-tint, tint, 3)
    return _rgb(*np.clip(g + t, 0.0, 1.0))


def _material(kind: str, rng: np.random.Generator) -> Material:
    """One material of `kind`, its fields drawn as the module's table says."""
    scale = _u(rng, (8.0, 60.0))
    if kind == "painted":
        rgb = colorsys.hsv_to_rgb(rng.uniform(), rng.uniform(0.0, 0.5), rng.uniform(0.08, 0.9))
        return Material(
            kind, _rgb(*rgb), _r(_u(rng, (0.05, 0.4))), _r(_u(rng, (8, 64)), 1),
            _r(_u(rng, (0.0, 0.06))), 0.0, 0.0, 0.002, _r(scale, 2), 1.0,
        )  # fmt: skip
    if kind == "print_grey":
        return Material(
            kind, _grey(rng, 0.42, 0.68, 0.02), _r(_u(rng, (0.0, 0.06))), _r(_u(rng, (4, 16)), 1),
            _r(_u(rng, (0.02, 0.08))), 0.0, _r(_u(rng, (0.02, 0.08))), _r(_u(rng, (0.001, 0.004)), 5),
            _r(scale, 2), 1.0,
        )  # fmt: skip
    if kind == "aluminium_bare":
        return Material(
            kind, _grey(rng, 0.55, 0.78, 0.03), _r(_u(rng, (0.5, 0.9))), _r(_u(rng, (40, 250)), 1),
            _r(_u(rng, (0.03, 0.12))), 0.0, 0.0, 0.002, _r(scale, 2), _r(_u(rng, (10.0, 40.0)), 1),
        )  # fmt: skip
    if kind == "aluminium_anodised":
        hue = {"black": 0.0, "blue": 0.6, "red": 0.0, "gold": 0.11, "clear": 0.0}
        sat = {"black": 0.0, "blue": 0.6, "red": 0.7, "gold": 0.6, "clear": 0.05}
        colour = str(rng.choice(list(hue)))
        value = rng.uniform(0.06, 0.15) if colour == "black" else rng.uniform(0.25, 0.6)
        rgb = colorsys.hsv_to_rgb(hue[colour], sat[colour], value)
        return Material(
            kind, _rgb(*rgb), _r(_u(rng, (0.2, 0.5))), _r(_u(rng, (24, 96)), 1),
            _r(_u(rng, (0.0, 0.05))), 0.0, 0.0, 0.002, _r(scale, 2), 1.0,
        )  # fmt: skip
    if kind == "mli":
        rgb = (0.80, 0.58, 0.22) if rng.uniform() < 0.6 else (0.78, 0.78, 0.80)  # kapton gold, silver
        return Material(
            kind, _rgb(*rgb), _r(_u(rng, (0.6, 1.0))), _r(_u(rng, (80, 400)), 1),
            _r(_u(rng, (0.05, 0.2))), _r(_u(rng, (0.15, 0.5))), 0.0, 0.002, _r(_u(rng, (15.0, 50.0)), 2), 1.0,
        )  # fmt: skip
    if kind == "as_built":
        return Material(kind, (0.0, 0.0, 0.0), 0.0, 48.0, 0.0, 0.0, 0.0, 0.002, _r(scale, 2), 1.0)
    raise ValueError(f"unknown material kind {kind!r}")


def _tint(rng: np.random.Generator) -> tuple[float, float, float]:
    """A lamp's colour between a warm halogen's and a cool LED's (max channel 1)."""
    warm, cool = np.array([1.0, 0.78, 0.55]), np.array([0.86, 0.93, 1.0])
    c = warm + rng.uniform() * (cool - warm)
    return _rgb(*(c / c.max()))


def _lamp(mount: str, rng: np.random.Generator, d: LookDistribution) -> Lamp:
    if mount == "at_camera":
        # within lamp_at_camera_m of the lens, in the image plane (a ring light or a lamp beside it)
        r, phi = d.lamp_at_camera_m * np.sqrt(rng.uniform()), rng.uniform(0, 2 * np.pi)
        pos = (r * np.cos(phi), r * np.sin(phi), 0.0)
        mount_frame = "camera"
    elif mount == "off_camera" and rng.uniform() < 0.5:
        r, phi = _u(rng, d.lamp_off_camera_m), rng.uniform(0, 2 * np.pi)
        pos = (r * np.cos(phi), r * np.sin(phi), rng.uniform(-0.3, 0.3))
        mount_frame = "camera"
    else:
        # fixed in the lab, on the camera's side of the berthing plane (-Z_t)
        dist, off = _u(rng, d.lamp_world_m), np.radians(_u(rng, d.lamp_world_off_axis_deg))
        phi = rng.uniform(0, 2 * np.pi)
        pos = (dist * np.sin(off) * np.cos(phi), dist * np.sin(off) * np.sin(phi), -dist * np.cos(off))
        mount_frame = "world"
    aim = tuple(_r(x) for x in rng.uniform(-d.lamp_aim_m, d.lamp_aim_m, 3))
    cone = _u(rng, d.lamp_cone_deg)
    return Lamp(
        mount_frame,
        _rgb(*pos),
        (aim[0], aim[1], aim[2]),
        _r(_u(rng, d.lamp_irradiance)),
        _tint(rng),
        _r(cone, 2),
        _r(cone * _u(rng, d.lamp_soft), 2),
    )


def draw(rng: np.random.Generator, d: LookDistribution = DEFAULT) -> LookParams:
    """One look, every axis drawn from `rng` in a fixed order (so a seed names a look)."""
    seed = int(rng.integers(1 << 31))
    scheme = "uniform" if rng.uniform() < d.p_uniform_scheme else "per_part"
    if scheme == "uniform":
        one = _material(str(rng.choice(MATERIAL_KINDS, p=d.p_kind)), rng)
        materials = tuple((name, one) for name in FIXTURE_PARTS)
    else:
        materials = tuple(
            (name, _material(str(rng.choice(MATERIAL_KINDS, p=d.p_kind)), rng)) for name in FIXTURE_PARTS
        )
    lighting = str(rng.choice(LIGHTINGS, p=d.p_lighting))
    sun_scale = earth_scale = 0.0
    lamps: tuple[Lamp, ...] = ()
    if lighting in ("sun_earth", "sun"):
        sun_scale = _u(rng, d.sun_scale)
    if lighting == "sun_earth":
        earth_scale = _u(rng, d.earth_scale)
    if lighting == "earth":
        earth_scale = _u(rng, d.earth_alone_scale)
    if lighting == "lamp_at_camera":
        lamps = (_lamp("at_camera", rng, d),)
    if lighting == "lamp_off_camera":
        lamps = (_lamp("off_camera", rng, d),)
    if lighting == "lamps":
        n = int(rng.integers(2, MAX_LAMPS + 1))
        lamps = tuple(_lamp(str(rng.choice(["at_camera", "off_camera"])), rng, d) for _ in range(n))
    ambient = _u(rng, d.ambient_lamps if lamps else d.ambient_space)
    backdrop = str(rng.choice(BACKDROPS, p=d.p_backdrop))
    backdrop_seed = int(rng.integers(1 << 31))
    gain = _u(rng, d.backdrop_gain) if backdrop in ("stars", "clutter", "perlin") else 1.0
    exposure = float(np.exp(rng.uniform(*np.log(d.exposure))))
    vignetting = _u(rng, d.vignetting) if rng.uniform() < d.p_vignetting else 0.0
    k1 = 0.0
    if rng.uniform() < d.p_distortion:
        # k1 from the displacement at the corner: r_d - r_u = k1 r_u^3 (normalised radius) x f
        corner_px = _u(rng, d.distortion_corner_px) * float(rng.choice([-1.0, 1.0]))
        r = CORNER_RADIUS_PX / F_PX
        k1 = corner_px / (r**3 * F_PX)
    return LookParams(
        seed=seed,
        scheme=scheme,
        materials=materials,
        lighting=lighting,
        sun_scale=_r(sun_scale),
        earth_scale=_r(earth_scale),
        ambient=_r(ambient),
        lamps=lamps,
        backdrop=backdrop,
        backdrop_seed=backdrop_seed,
        backdrop_gain=_r(gain),
        exposure=_r(exposure),
        vignetting=_r(vignetting),
        distortion_k1=_r(k1, 7),
    )


def look_for(seed: int, d: LookDistribution = DEFAULT) -> LookParams:
    """The look a sequence spec with this look seed renders (its own stream of the seed)."""
    return draw(np.random.default_rng([int(seed), LOOK_STREAM]), d)


def corner_displacement_px(k1: float) -> float:
    """How far the distortion moves the image's corner, pixels (signed: + outwards)."""
    r = CORNER_RADIUS_PX / F_PX
    return float(k1 * r**3 * F_PX)


# ----------------------------------------------------------------------------- contact sheet, cost
SHEET_RANGES_M = (0.7, 1.0, 1.5, 2.2)  # the tiles' ranges, cycling: the fixture large enough to judge


def _frames_near(plan: Any, range_m: float, n: int) -> list[int]:
    """`n` consecutive frames of the plan from the one nearest `range_m`."""
    k = int(np.argmin(np.abs(plan.range_m - range_m)))
    k = min(k, plan.n_frames - n)
    return list(range(max(k, 0), max(k, 0) + n))


def contact_sheet(
    spec_file: str, out: str, n: int = 24, cols: int = 6, scale: int = 3, bench_frames: int = 0
) -> dict[str, float]:
    """The first `n` scenes of a scene file, one frame each (a range of SHEET_RANGES_M), in
    their randomised looks with the fixture's keypoints projected from the label (crosses: red
    on the berthing plane, cyan the throat), as a grid of 1/`scale` thumbnails written to `out`.
    With `bench_frames`, each scene's frames around that one are also drawn in the default look
    and in its own, and the median CPU milliseconds a frame of each are returned (CPU time, all
    threads of this process: it depends less on other jobs than the wall clock does)."""
    import time

    from PIL import Image, ImageDraw

    from oibar.geometry.fixture import keypoints_m
    from oibar.geometry.rotations import quat_to_matrix

    from .dataset import load_spec_file, load_spec_scene, plan_sequence, spec_look
    from .meshes import scene_parts
    from .ports import PORTS
    from .render import Renderer

    specs = load_spec_file(Path(spec_file))[:n]
    r = Renderer(_CAM)
    cam = r.camera
    tw, th = cam.width_px // scale, cam.height_px // scale
    rows = (len(specs) + cols - 1) // cols
    sheet = Image.new("RGB", (cols * tw, rows * th))
    times: dict[str, list[float]] = {"default": [], "randomized": []}
    kp = keypoints_m()
    for i, spec in enumerate(specs):
        plan = plan_sequence(spec)
        frames = _frames_near(plan, SHEET_RANGES_M[i % len(SHEET_RANGES_M)], max(1, bench_frames))
        port = PORTS[spec.port]
        parts = scene_parts(spec.background, spec.port)
        look = spec_look(spec)

        def draw(k: int, plan: Any = plan) -> np.ndarray:
            return r.render(
                plan.R_lvlh_cam[k], plan.p_lvlh_cam[k], plan.sun_lvlh[k], plan.R_ecef_lvlh[k],
                plan.earth_center_lvlh_km,
            )  # fmt: skip

        if bench_frames:
            r.load_scene(parts, spec.background, port.p_lvlh_t, perlin_seed=spec.seed)
            for k in frames:
                t = time.process_time()
                draw(k)
                times["default"].append(time.process_time() - t)
        load_spec_scene(r, spec)  # its own look, as the generator draws it
        for k in frames:
            t = time.process_time()
            img = draw(k)
            times["randomized"].append(time.process_time() - t)
        k = frames[0]
        uv = cam.project(kp @ quat_to_matrix(plan.q_cam_target[k]).T + plan.T_cam_target[k])
        tile = Image.fromarray(img).resize((tw, th), Image.Resampling.BILINEAR)
        d = ImageDraw.Draw(tile)
        for j, (u, v) in enumerate(uv / scale):
            c = (0, 255, 255) if j == len(kp) - 1 else (255, 40, 40)
            d.line([(u - 2, v), (u + 2, v)], fill=c)
            d.line([(u, v - 2), (u, v + 2)], fill=c)
        label = f"{spec.name} {look.lighting} {look.backdrop}" if look else spec.name
        d.text((3, 2), label, fill=(255, 255, 0))
        sheet.paste(tile, ((i % cols) * tw, (i // cols) * th))
    r.release()
    sheet.save(out, optimize=True)
    return {k: 1000.0 * float(np.median(v)) for k, v in times.items() if v}


def main(argv: list[str] | None = None) -> int:
    import argparse

    from .render import set_llvmpipe_threads

    ap = argparse.ArgumentParser(
        prog="python -m oibar_hil.randomize",
        description="Draw a look, or write a contact sheet of a scene file's randomised looks.",
    )
    ap.add_argument("--seed", type=int, help="print the look this look seed draws")
    ap.add_argument("--sheet", help="write a contact sheet PNG here")
    ap.add_argument("--spec", default="models/scenes/train_dr.json", help="scene file for --sheet")
    ap.add_argument("-n", type=int, default=24, help="scenes on the sheet")
    ap.add_argument("--bench", type=int, default=0, metavar="FRAMES", help="also time FRAMES frames a scene")
    args = ap.parse_args(argv)
    if args.seed is not None:
        import json

        print(json.dumps(look_for(args.seed).as_dict(), indent=1))
    if args.sheet:
        set_llvmpipe_threads(1)  # the data set's workers run one llvmpipe thread each
        ms = contact_sheet(args.spec, args.sheet, args.n, bench_frames=args.bench)
        print(
            f"wrote {args.sheet}" + "".join(f"; {k} {v:.1f} CPU ms a frame (median)" for k, v in ms.items())
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
