"""Procedural textures (Perlin fractal noise via FastNoiseLite), equirectangular and sampled by
direction so they are seamless on the sphere: the Earth's surface and clouds, and the `perlin`
background of the paper's second subset."""

from __future__ import annotations

import numpy as np
from pyfastnoiselite.pyfastnoiselite import FastNoiseLite, FractalType, NoiseType


def _sphere_points(width: int, height: int) -> np.ndarray:
    """(3, H*W) unit vectors for an equirectangular grid; row 0 is latitude +90."""
    lon = (np.arange(width) + 0.5) / width * 2 * np.pi - np.pi
    lat = np.pi / 2 - (np.arange(height) + 0.5) / height * np.pi
    lon_g, lat_g = np.meshgrid(lon, lat)
    pts = np.stack([np.cos(lat_g) * np.cos(lon_g), np.cos(lat_g) * np.sin(lon_g), np.sin(lat_g)])
    return pts.reshape(3, -1).astype(np.float32)


def _fbm(seed: int, pts: np.ndarray, frequency: float, octaves: int) -> np.ndarray:
    n = FastNoiseLite(seed)
    n.noise_type = NoiseType.NoiseType_Perlin
    n.fractal_type = FractalType.FractalType_FBm
    n.fractal_octaves = octaves
    n.frequency = frequency
    return np.asarray(n.gen_from_coords(pts), dtype=np.float32)


def earth_texture(seed: int = 7, width: int = 1024, height: int = 512) -> np.ndarray:
    """RGBA uint8: RGB ground colour (ocean, land, ice), A cloud cover."""
    pts = _sphere_points(width, height)
    land = _fbm(seed, pts, 1.6, 7)
    cloud = _fbm(seed + 1, pts * np.array([[1.0], [1.0], [2.5]], dtype=np.float32), 2.5, 7)
    lat = np.abs(pts[2])
    ocean = np.array([0.03, 0.10, 0.28])
    green = np.array([0.18, 0.26, 0.10])
    desert = np.array([0.50, 0.42, 0.28])
    is_land = land > 0.04
    dry = np.clip((0.5 - lat) * 2.0, 0, 1)[:, None] * np.clip(land * 4, 0, 1)[:, None]
    rgb = np.where(is_land[:, None], green * (1 - dry) + desert * dry, ocean)
    rgb = np.where((lat > 0.92)[:, None], np.array([0.85, 0.88, 0.92]), rgb)
    alpha = np.clip((cloud + 0.05) * 2.2, 0.0, 1.0) ** 1.5
    out = np.concatenate([rgb, alpha[:, None]], axis=1).reshape(height, width, 4)
    return (np.clip(out, 0, 1) * 255 + 0.5).astype(np.uint8)


def earth_ground(rgba: np.ndarray) -> np.ndarray:
    """(H, W, 3) float: the Earth's Lambertian albedo per texel of `earth_texture`'s RGBA, the
    ground's colour under clouds of albedo 0.95 (its cover, A, mixes them)."""
    px = np.asarray(rgba) / 255.0
    out: np.ndarray = px[..., :3] * (1 - px[..., 3:4]) + 0.95 * px[..., 3:4]
    return out


def sample_equirect(image: np.ndarray, d: np.ndarray) -> np.ndarray:
    """`image`'s nearest texel (row 0 at latitude +90, column 0 at longitude -180) in each of
    the unit directions `d` (..., 3) of its own frame: the mapping the renderers' background
    shader and Mitsuba's environment use."""
    d = np.asarray(d, float)
    lon = np.arctan2(d[..., 1], d[..., 0]) / (2 * np.pi) + 0.5
    lat = 0.5 - np.arcsin(np.clip(d[..., 2], -1, 1)) / np.pi
    h, w = image.shape[:2]
    out: np.ndarray = image[
        np.clip((lat * h).astype(int), 0, h - 1), np.clip((lon * w).astype(int), 0, w - 1)
    ]
    return out


def box_downsample(image: np.ndarray, k: int) -> np.ndarray:
    """Mean of each k x k block (H and W divisible by k)."""
    h, w = image.shape[:2]
    out: np.ndarray = image.reshape(h // k, k, w // k, k, *image.shape[2:]).mean(axis=(1, 3))
    return out


def perlin_background(seed: int, width: int = 1024, height: int = 512) -> np.ndarray:
    """RGB uint8 backdrop for the `perlin` subset: fractal Perlin noise between two random
    colours, with a second noise field modulating brightness. One per sequence seed."""
    rng = np.random.default_rng(seed)
    pts = _sphere_points(width, height)
    f1 = float(rng.uniform(2.0, 6.0))
    f2 = float(rng.uniform(4.0, 12.0))
    a = _fbm(int(rng.integers(1 << 30)), pts, f1, 4)
    b = _fbm(int(rng.integers(1 << 30)), pts, f2, 3)
    c0, c1 = rng.uniform(0.0, 1.0, 3), rng.uniform(0.0, 1.0, 3)
    t = np.clip(a * 1.4 + 0.5, 0, 1)[:, None]
    rgb = (c0 * (1 - t) + c1 * t) * np.clip(0.65 + 1.2 * b, 0.2, 1.2)[:, None]
    return (np.clip(rgb, 0, 1).reshape(height, width, 3) * 255 + 0.5).astype(np.uint8)


# ----------------------------------------------------------------------------- randomised looks
def periodic_noise3d(seed: int, size: int = 64, slope: float = 1.6) -> np.ndarray:
    """RGBA uint8 (size^3 x 4): four independent fBm fields on a periodic 3-D grid (Fourier
    synthesis, amplitude ~ |k|^-slope), so a texture that repeats draws no seam. R is a surface's
    grain, G, B, A a bump vector (randomize.Material)."""
    rng = np.random.default_rng(seed)
    k = np.fft.fftfreq(size) * size
    kk = np.sqrt(k[:, None, None] ** 2 + k[None, :, None] ** 2 + k[None, None, :] ** 2)
    amp = np.where(kk > 0, np.maximum(kk, 1.0) ** -slope, 0.0)
    out = np.empty((size, size, size, 4), dtype=np.uint8)
    for c in range(4):
        spec = amp * np.exp(2j * np.pi * rng.uniform(size=amp.shape))
        f = np.fft.ifftn(spec).real
        f = (f - f.mean()) / (3.0 * f.std())  # about +-1 at 3 sigma
        out[..., c] = (np.clip(f * 0.5 + 0.5, 0, 1) * 255 + 0.5).astype(np.uint8)
    return out


def star_background(seed: int, width: int = 4096, height: int = 2048, n_stars: int = 9000) -> np.ndarray:
    """RGB uint8 equirectangular star field: stars uniform on the sphere, brightness from a power
    law (many faint, few bright), colour from bluish to reddish white. About one texel per camera
    pixel at this size (11 texels a degree against the camera's 10 pixels)."""
    rng = np.random.default_rng(seed)
    lon = rng.uniform(0.0, 1.0, n_stars)
    lat = np.arcsin(rng.uniform(-1.0, 1.0, n_stars))  # uniform in solid angle
    col = (lon * width).astype(int) % width
    row = np.clip(((0.5 - lat / np.pi) * height).astype(int), 0, height - 1)
    bright = np.clip(0.12 * rng.pareto(1.5, n_stars) + 0.1, 0.0, 1.0)
    tint = np.array([0.85, 0.9, 1.0]) + rng.uniform(0.0, 1.0, (n_stars, 1)) * np.array([0.15, 0.05, -0.2])
    img = np.zeros((height, width, 3), dtype=np.float32)
    img[row, col] = bright[:, None] * tint
    return (np.clip(img, 0, 1) * 255 + 0.5).astype(np.uint8)


def lab_clutter_background(seed: int, width: int = 2048, height: int = 1024) -> np.ndarray:
    """RGB uint8 equirectangular lab room: dim walls (darker towards the floor), boxes and racks
    of equipment in greys and muted colours, a few bright lamp strips and cables, all with a
    little fBm grain. A procedural stand-in for what stands behind a mock-up in a lab."""
    rng = np.random.default_rng(seed)
    lat = np.pi / 2 - (np.arange(height) + 0.5) / height * np.pi
    wall = rng.uniform(0.05, 0.3)
    base = wall * (0.55 + 0.45 * np.clip(0.5 + lat / np.pi * 1.5, 0, 1))  # floor darker
    img = np.repeat(base[:, None], width, axis=1)[..., None] * np.ones(3, dtype=np.float32)
    for _ in range(int(rng.integers(30, 80))):  # equipment, racks, boxes, doors
        w = int(rng.uniform(0.01, 0.12) * width)
        h = int(rng.uniform(0.03, 0.3) * height)
        x = int(rng.integers(0, width))
        y = int(rng.uniform(0.35, 0.9) * height) - h // 2  # around and below the horizon
        grey = rng.uniform(0.02, 0.6)
        colour = grey * (1.0 + rng.uniform(-0.25, 0.25, 3))
        cols = np.arange(x, x + w) % width
        img[max(0, y) : max(0, y + h), cols] = np.clip(colour, 0, 1)
    for _ in range(int(rng.integers(2, 7))):  # lamp strips near the ceiling
        w, h = int(rng.uniform(0.02, 0.08) * width), max(2, int(0.006 * height))
        x, y = int(rng.integers(0, width)), int(rng.uniform(0.05, 0.3) * height)
        img[y : y + h, np.arange(x, x + w) % width] = rng.uniform(0.85, 1.0)
    for _ in range(int(rng.integers(5, 20))):  # cables: thin dark curves
        x0, amp = rng.uniform(0, width), rng.uniform(5, 60)
        xs = np.arange(int(rng.uniform(0.05, 0.3) * width))
        ys = (rng.uniform(0.4, 0.9) * height + amp * np.sin(xs / rng.uniform(20, 120))).astype(int)
        img[np.clip(ys, 0, height - 1), (x0 + xs).astype(int) % width] = rng.uniform(0.0, 0.08)
    grain = _fbm(int(rng.integers(1 << 30)), _sphere_points(width, height), 24.0, 3).reshape(height, width)
    img *= np.clip(1.0 + 0.25 * grain, 0.5, 1.5)[..., None]
    return (np.clip(img, 0, 1) * 255 + 0.5).astype(np.uint8)
