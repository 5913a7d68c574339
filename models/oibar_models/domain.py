"""Domain randomisation, the image-space part (issue 58, part 3): what a camera and a world we did
not render do to a crop, drawn with albumentations (two texture axes our own, in its interface),
seeded per sample.

The estimator held on our renderer's frames and failed on a path tracer's and on a lab's: the
network had learnt one look. The renderer's own axes (materials, lamps, backgrounds) belong to
the data generator; these are the ones that act on the pixels, each a documented distribution:

| axis | transform | drawn | p |
| --- | --- | --- | ---: |
| texture | RandConv | 3->3 conv, kernel 1, 3 or 5 px, N(0, 1/(3 k^2)); blend alpha U(0, 1) | 0.2 |
| spectrum | FourierMix | low-frequency amplitude, half-side beta U(0.01, 0.15); mix lambda U(0, 1) | 0.2 |
| white balance | PlanckianJitter | black-body 3000-15000 K (a lab lamp to shade) | 0.3 |
| exposure and colour | ColorJitter | brightness, contrast, saturation +-30 %, hue +-3 % | 0.5 |
| sensor response | RandomGamma, RandomToneCurve | gamma 0.7-1.5; a tone curve's knee +-0.1 | 0.3, 0.2 |
| glare | RandomSunFlare | a flare of 1-3 circles anywhere in the crop | 0.1 |
| occlusion | CoarseDropout | 1-3 holes of 5-20 % of the side, black or grey | 0.2 |
| motion blur | MotionBlur | kernel 3-7 px, any direction | 0.2 |
| defocus | Defocus | radius 1-3 px | 0.15 |
| sensor noise | ISONoise, GaussNoise | colour shift 0.01-0.05, intensity 0.1-0.5; sigma 2-8 % | 0.2, 0.2 |
| compression | ImageCompression | JPEG quality 30-90 | 0.3 |

Every transform moves pixels' values only, never the fixture's points: the keypoint labels stay
as they are. Lens distortion and vignetting depend on where the crop lies in the frame; they
belong to the frame, not the crop (the generator's camera).

The two texture axes are ours, and come first (a surface or a light we did not render, before
the camera's effects):

- RandConv (Xu et al., ICLR 2021, the mixing variant): the crop through a random 3->3
  convolution, blended with itself by alpha, then set to the crop's own per-channel mean and std
  (the convolution's scale and sign are arbitrary). The paper's kernels would also shift the
  image, by up to (k - 1) / 2 px where a kernel's weight lies off its centre: label error for a
  keypoint. Ours are made point-symmetric (zero phase): they blur, sharpen, find edges and mix
  colours, and move nothing.
- FourierMix (the amplitude mix of Xu et al., CVPR 2021; FDA, Yang and Soatto, CVPR 2020, is
  lambda 1): the amplitude of the frequencies |f_y|, |f_x| <= beta x the crop's side (at least
  the first harmonic; beta 0.15 is 19 of a 128 px crop's 64) becomes (1 - lambda) the crop's +
  lambda a reference's; the crop's phase, where its geometry lies, is kept. The reference: a
  random fBm colour field drawn from the same seed (no data needed), or a crop from a pool given
  to DomainAugment(refs=...). Lambda uniform over the whole of [0, 1] (Xu et al.'s eta 1); beta
  from 0.01 (the mean colour and the first harmonic) to 0.15 (shading and coarse texture): what
  a lamp, a paint or a backdrop changes, while the edges stay.

`DomainAugment()(crop, seed)`: the same seed gives the same image, on any worker.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import albumentations as A
import cv2
import numpy as np
import scipy.fft as sfft  # float32 transforms (numpy's are float64 only); albumentations needs scipy

# The pipeline's order (compose()).
AXES = (
    "RandConv",
    "FourierMix",
    "PlanckianJitter",
    "ColorJitter",
    "RandomGamma",
    "RandomToneCurve",
    "RandomSunFlare",
    "CoarseDropout",
    "MotionBlur",
    "Defocus",
    "ISONoise",
    "GaussNoise",
    "ImageCompression",
)
# Each axis's seed slot, in the order the axes were added rather than the pipeline's: a new axis
# takes a new slot, and every older one draws for a seed what it drew before (SeedSequence's
# words do not depend on how many are asked for).
SEED_SLOTS = (
    "PlanckianJitter",
    "ColorJitter",
    "RandomGamma",
    "RandomToneCurve",
    "RandomSunFlare",
    "CoarseDropout",
    "MotionBlur",
    "Defocus",
    "ISONoise",
    "GaussNoise",
    "ImageCompression",
    "RandConv",
    "FourierMix",
)


def _mean_std(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-channel mean and standard deviation (float32) of an (H, W, C <= 4) image; cv2's, as
    numpy's reductions over two axes cost ~10x as much."""
    m, s = cv2.meanStdDev(np.ascontiguousarray(x))
    return m.ravel().astype(np.float32), s.ravel().astype(np.float32)


def _standardise_like(y: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """`y` (H, W, C) moved to `ref`'s per-channel mean and standard deviation."""
    (my, sy), (mr, sr) = _mean_std(y), _mean_std(ref)
    out: np.ndarray = (y - my) * (sr / np.maximum(sy, 1e-6)) + mr
    return out


def _to_uint8(x: np.ndarray) -> np.ndarray:
    out: np.ndarray = np.clip(np.rint(x), 0, 255).astype(np.uint8)
    return out


def rand_conv(img: np.ndarray, weights: np.ndarray, alpha: float) -> np.ndarray:
    """`img` (H, W, 3) uint8 through a 3->3 convolution `weights` (out, in, k, k), k odd, blended
    with itself by `alpha` (1: the crop as it was) and set to the crop's per-channel mean/std."""
    x = img.astype(np.float32)
    w = weights.astype(np.float32)
    # cv2 correlates (the same as convolving, for our point-symmetric kernels); reflected borders,
    # as zeros would draw a dark frame that the network could take for an edge
    y = np.stack(
        [
            sum(cv2.filter2D(x[..., i], -1, w[o, i], borderType=cv2.BORDER_REFLECT_101) for i in range(3))
            for o in range(3)
        ],
        axis=-1,
    )
    # the convolution's scale and the sign of its mean are arbitrary: it gets the crop's range
    # before the blend, so that alpha weighs two images alike, and the blend after, as it loses
    # contrast where the two disagree
    b = alpha * x + (1.0 - alpha) * _standardise_like(y, x)
    return _to_uint8(_standardise_like(b, x))


def fbm_field(rng: np.random.Generator, h: int, w: int) -> np.ndarray:
    """A random colour field (H, W, 3), float 0-255: fractal noise (amplitude ~ f^-s, s U(1, 2):
    natural images' 1 to cloud-smooth 2), one grey pattern or one per channel or between, on a
    random mean colour."""
    f = np.hypot(np.fft.fftfreq(h)[:, None], np.fft.rfftfreq(w)[None, :])
    f[0, 0] = 1.0
    gain = (f ** -rng.uniform(1.0, 2.0)).astype(np.float32)
    gain[0, 0] = 0.0  # the mean is set below
    # white noise drawn as its spectrum (real and imaginary parts side by side), saving a transform
    white = rng.standard_normal((h, w // 2 + 1, 4, 2), dtype=np.float32).view(np.complex64)[..., 0]
    noise = sfft.irfft2(white * gain[..., None], s=(h, w), axes=(0, 1))
    noise /= np.maximum(_mean_std(noise)[1], 1e-9)
    tint = rng.uniform(0.0, 1.0)  # 0: one grey pattern in every channel, 1: each its own
    n = (1.0 - tint) * noise[..., :1] + tint * noise[..., 1:]
    n /= np.maximum(_mean_std(n)[1], 1e-9)
    mean = rng.uniform(0.1, 0.9, 3) * 255.0
    std = rng.uniform(0.03, 0.25, 3) * 255.0
    out: np.ndarray = np.clip(mean + std * n, 0.0, 255.0)
    return out


def fourier_mix(img: np.ndarray, ref: np.ndarray, lam: float, beta: float) -> np.ndarray:
    """`img` (H, W, 3) uint8 with the amplitude of its frequencies |f_y|, |f_x| <= beta x its side
    (rounded, at least the first harmonic) mixed as (1 - lam) img + lam `ref` (H, W, 3), its
    phase kept."""
    h, w = img.shape[:2]
    F = sfft.rfft2(img.astype(np.float32), axes=(0, 1))
    R = sfft.rfft2(np.asarray(ref, np.float32), axes=(0, 1))
    b = int(np.clip(round(beta * min(h, w)), 1, min(h, w) // 2 - 1))
    # the square about DC: rows 0..b and -b..-1, columns 0..b of the half spectrum (irfft2 takes
    # the other half as the conjugate, so the result stays real)
    sel = np.ix_(np.r_[0 : b + 1, h - b : h], np.arange(b + 1))
    amp = (1.0 - lam) * np.abs(F[sel]) + lam * np.abs(R[sel])
    F[sel] = amp * np.exp(1j * np.angle(F[sel]))
    return _to_uint8(sfft.irfft2(F, s=(h, w), axes=(0, 1)))


class RandConv(A.ImageOnlyTransform):
    """Random-convolution texture (Xu et al., ICLR 2021, the mixing variant), point-symmetric
    kernels so that nothing moves (module docstring)."""

    def __init__(self, kernel_sizes: Sequence[int] = (1, 3, 5), p: float = 0.2) -> None:
        super().__init__(p=p)
        self.kernel_sizes = tuple(int(k) for k in kernel_sizes)

    def get_params(self) -> dict[str, Any]:
        g = self.random_generator
        k = int(g.choice(self.kernel_sizes))
        wt = g.normal(0.0, 1.0 / np.sqrt(3 * k * k), (3, 3, k, k))
        # point-symmetric: an off-centre weight would shift the image (labels stay where they are)
        wt = 0.5 * (wt + wt[:, :, ::-1, ::-1])
        return {"weights": wt, "alpha": float(g.uniform(0.0, 1.0))}

    def apply(self, img: np.ndarray, weights: np.ndarray, alpha: float, **params: Any) -> np.ndarray:
        return rand_conv(img, weights, alpha)

    def get_transform_init_args_names(self) -> tuple[str, ...]:
        return ("kernel_sizes",)


class FourierMix(A.ImageOnlyTransform):
    """Low-frequency amplitude mixing with a reference (a random fBm colour field unless a pool of
    crops is given); the crop's phase, and so its geometry, kept."""

    def __init__(
        self,
        beta: tuple[float, float] = (0.01, 0.15),
        refs: Sequence[np.ndarray] | None = None,
        p: float = 0.2,
    ) -> None:
        super().__init__(p=p)
        self.beta = beta
        self.refs = list(refs) if refs else None

    def get_params_dependent_on_data(self, params: dict[str, Any], data: dict[str, Any]) -> dict[str, Any]:
        g = self.random_generator
        h, w = data["image"].shape[:2]
        lam, beta = float(g.uniform(0.0, 1.0)), float(g.uniform(*self.beta))
        if self.refs:
            ref = np.asarray(self.refs[int(g.integers(len(self.refs)))])
            if ref.shape[:2] != (h, w):
                ref = cv2.resize(ref, (w, h), interpolation=cv2.INTER_AREA)
        else:
            ref = fbm_field(g, h, w)
        return {"ref": ref, "lam": lam, "beta": beta}

    def apply(self, img: np.ndarray, ref: np.ndarray, lam: float, beta: float, **params: Any) -> np.ndarray:
        return fourier_mix(img, ref, lam, beta)

    def get_transform_init_args_names(self) -> tuple[str, ...]:
        return ("beta",)


def compose(refs: Sequence[np.ndarray] | None = None) -> Any:
    """The pipeline of the table above (its RNG seeded per call by DomainAugment). `refs`: crops
    (H, W, 3) uint8 whose amplitude FourierMix borrows instead of a random field's."""
    return A.Compose(
        [
            RandConv(kernel_sizes=(1, 3, 5), p=0.2),
            FourierMix(beta=(0.01, 0.15), refs=refs, p=0.2),
            A.PlanckianJitter(mode="blackbody", temperature_limit=(3000, 15000), p=0.3),
            A.ColorJitter(brightness=0.3, contrast=0.3, saturation=0.3, hue=0.03, p=0.5),
            A.RandomGamma(gamma_limit=(70, 150), p=0.3),
            A.RandomToneCurve(scale=0.1, p=0.2),
            A.RandomSunFlare(
                flare_roi=(0.0, 0.0, 1.0, 1.0), num_flare_circles_range=(1, 3), src_radius=24, p=0.1
            ),
            A.CoarseDropout(
                num_holes_range=(1, 3),
                hole_height_range=(0.05, 0.2),
                hole_width_range=(0.05, 0.2),
                fill="random_uniform",
                p=0.2,
            ),
            A.MotionBlur(blur_limit=(3, 7), p=0.2),
            A.Defocus(radius=(1, 3), p=0.15),
            A.ISONoise(color_shift=(0.01, 0.05), intensity=(0.1, 0.5), p=0.2),
            A.GaussNoise(std_range=(0.02, 0.08), p=0.2),
            A.ImageCompression(quality_range=(30, 90), p=0.3),
        ],
        seed=0,
    )


class DomainAugment:
    """The pipeline, built once; each call seeded, so a sample's draw depends on its seed alone.
    `refs`: FourierMix's pool of reference crops (default: a random field drawn from the seed)."""

    def __init__(self, refs: Sequence[np.ndarray] | None = None) -> None:
        self._t = compose(refs)
        self._slots = [SEED_SLOTS.index(type(t).__name__) for t in self._t.transforms]

    def __call__(self, img_uint8: np.ndarray, seed: int) -> np.ndarray:
        if img_uint8.dtype != np.uint8 or img_uint8.ndim != 3 or img_uint8.shape[2] != 3:
            raise ValueError(f"expected an (H, W, 3) uint8 image, got {img_uint8.dtype} {img_uint8.shape}")
        # each transform its own stream: seeded alike (Compose.set_random_seed), their p draws
        # would be one number, and they would fire all together or none
        seeds = np.random.SeedSequence(int(seed)).generate_state(len(SEED_SLOTS))
        for tr, slot in zip(self._t.transforms, self._slots, strict=True):
            tr.set_random_seed(int(seeds[slot]))
        out: np.ndarray = self._t(image=np.ascontiguousarray(img_uint8))["image"]
        return out
