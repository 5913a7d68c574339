"""Domain randomisation, the image-space part (issue 58, part 3): what a camera and a world we did
not render do to a crop, drawn with albumentations, seeded per sample.

The estimator held on our renderer's frames and failed on a path tracer's and on a lab's: the
network had learnt one look. The renderer's own axes (materials, lamps, backgrounds) belong to
the data generator; these are the ones that act on the pixels, each a documented distribution:

| axis | transform | drawn | p |
| --- | --- | --- | ---: |
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

`DomainAugment()(crop, seed)`: the same seed gives the same image, on any worker.
"""

from __future__ import annotations

from typing import Any

import numpy as np

AXES = (
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


def compose() -> Any:
    """The albumentations pipeline of the table above (its RNG seeded per call by DomainAugment)."""
    import albumentations as A

    return A.Compose(
        [
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
    """The pipeline, built once; each call seeded, so a sample's draw depends on its seed alone."""

    def __init__(self) -> None:
        self._t = compose()

    def __call__(self, img_uint8: np.ndarray, seed: int) -> np.ndarray:
        if img_uint8.dtype != np.uint8 or img_uint8.ndim != 3 or img_uint8.shape[2] != 3:
            raise ValueError(f"expected an (H, W, 3) uint8 image, got {img_uint8.dtype} {img_uint8.shape}")
        # each transform its own stream: seeded alike (Compose.set_random_seed), their p draws
        # would be one number, and they would fire all together or none
        seeds = np.random.SeedSequence(int(seed)).generate_state(len(self._t.transforms))
        for tr, s in zip(self._t.transforms, seeds, strict=True):
            tr.set_random_seed(int(s))
        out: np.ndarray = self._t(image=np.ascontiguousarray(img_uint8))["image"]
        return out
