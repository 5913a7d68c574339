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
