"""Domain randomisation of the crops (oibar_models.domain): seeded, every axis drawn, labels
untouched, and off unless a config asks (the crops of every model trained so far unchanged)."""

from dataclasses import replace

import albumentations as A
import numpy as np
import pytest

from oibar_models.domain import (
    AXES,
    SEED_SLOTS,
    DomainAugment,
    FourierMix,
    RandConv,
    compose,
    fbm_field,
    fourier_mix,
    rand_conv,
)
from oibar_models.kp_data import CropAugment, photometric


def _crop(seed=0):
    rng = np.random.default_rng(seed)
    img = np.full((128, 128, 3), 60, np.uint8)
    img[30:100, 20:110] = (rng.random((70, 90, 3)) * 120 + 100).astype(
        np.uint8
    )  # a bright fixture-like block
    return img


def test_the_pipeline_is_the_documented_table():
    assert tuple(type(t).__name__ for t in compose().transforms) == AXES


def test_a_seed_gives_one_image_and_the_axes_fire_independently():
    d, img = DomainAugment(), _crop()
    outs = [d(img, s) for s in range(120)]
    assert np.array_equal(d(img, 7), outs[7]) and outs[7].dtype == np.uint8 and outs[7].shape == img.shape
    unchanged = np.mean([np.array_equal(o, img) for o in outs])
    # each axis fires with its own p: all-or-nothing draws (one seed for all) left half unchanged
    assert unchanged < 0.12, unchanged
    assert len({o.tobytes() for o in outs}) > 100


def test_off_unless_asked_and_then_deterministic(monkeypatch):
    import oibar_models.kp_data as kp_data

    a = CropAugment()
    assert a.p_domain == 0.0
    img = _crop(1)

    def never():
        raise AssertionError("the domain pipeline ran with p_domain 0")

    with monkeypatch.context() as m:  # off: the pipeline never runs
        m.setattr(kp_data, "_domain", never)
        plain = [photometric(img, np.random.default_rng(s), a) for s in range(20)]
    on = replace(a, p_domain=1.0)
    first = [photometric(img, np.random.default_rng(s), on) for s in range(20)]
    second = [photometric(img, np.random.default_rng(s), on) for s in range(20)]
    assert all(np.array_equal(x, y) for x, y in zip(first, second, strict=True))
    assert sum(not np.array_equal(x, y) for x, y in zip(plain, first, strict=True)) >= 15


def test_a_bad_image_is_refused():
    with pytest.raises(ValueError, match="uint8"):
        DomainAugment()(np.zeros((8, 8, 3), np.float32), 0)


# --- the texture axes (RandConv, FourierMix) ----------------------------------------------------


def _rect():
    """A bright rectangle off the crop's centre, symmetric about its own (49.5, 79.5)."""
    img = np.full((128, 128, 3), 40, np.uint8)
    img[30:70, 50:110] = (200, 180, 160)
    return img


def _centroid(img):
    """Centroid (row, col) of what differs from the background, whatever its sign."""
    g = img.astype(float).mean(axis=2)
    w = np.abs(g - np.median(np.r_[g[:5].ravel(), g[-5:].ravel()]))
    rows, cols = np.mgrid[: g.shape[0], : g.shape[1]]
    return np.array([(w * rows).sum(), (w * cols).sum()]) / w.sum()


def _phase_shift(a, b):
    """The shift (rows, cols) at the peak of a and b's phase correlation, and the peak's height."""
    fa, fb = (np.fft.fft2(x.astype(float).mean(axis=2)) for x in (a, b))
    x = fa * np.conj(fb)
    r = np.abs(np.fft.ifft2(x / np.maximum(np.abs(x), 1e-9)))
    i = np.array(np.unravel_index(np.argmax(r), r.shape))
    return tuple((i + 64) % 128 - 64), r.max()


def _fired(t, img, seeds):
    outs = []
    for s in seeds:
        t.set_random_seed(s)
        outs.append(t(image=img)["image"])
    return outs


def test_randconv_moves_values_not_the_fixture():
    img = _rect()
    outs = _fired(RandConv(p=1.0), img, range(60))
    assert all(o.dtype == np.uint8 and o.shape == img.shape for o in outs)
    assert sum(not np.array_equal(o, img) for o in outs) > 50
    # (a two-tone rectangle through a 1x1 kernel can only be itself or inverted: variety on texture)
    assert len({o.tobytes() for o in _fired(RandConv(p=1.0), _crop(6), range(60))}) == 60
    # point-symmetric kernels: the rectangle stays centred where it was (exactly, but rounding)
    for o in outs:
        assert np.abs(_centroid(o) - _centroid(img)).max() < 0.1
    # the check sees a shift: the paper's kernels may put their weight off centre (here, all of it)
    corner = np.zeros((3, 3, 3, 3))
    corner[[0, 1, 2], [0, 1, 2], 0, 0] = 1.0
    assert np.abs(_centroid(rand_conv(img, corner, 0.0)) - _centroid(img)).max() > 0.9


def test_randconv_keeps_the_crops_range_and_alpha_one_is_the_crop():
    img = _crop(2)
    w = np.random.default_rng(0).normal(0, 1 / 3, (3, 3, 3, 3))
    w = 0.5 * (w + w[:, :, ::-1, ::-1])
    out = rand_conv(img, w, 0.3).astype(float)
    x = img.astype(float)
    # the crop's mean and std, but for what clipping to 0-255 takes
    assert np.allclose(out.mean(axis=(0, 1)), x.mean(axis=(0, 1)), atol=5.0)
    assert np.allclose(out.std(axis=(0, 1)), x.std(axis=(0, 1)), rtol=0.15)
    assert np.abs(rand_conv(img, w, 1.0).astype(int) - img).max() <= 1


def test_fourier_mix_keeps_the_phase_so_the_geometry():
    for img in (_rect(), _crop(3)):
        outs = _fired(FourierMix(p=1.0), img, range(60))
        assert all(o.dtype == np.uint8 and o.shape == img.shape for o in outs)
        assert sum(not np.array_equal(o, img) for o in outs) > 55
        for o in outs:
            shift, peak = _phase_shift(img, o)
            assert shift == (0, 0) and peak > 0.6, (shift, peak)
    # the check sees a shift of one pixel
    assert _phase_shift(_rect(), np.roll(_rect(), 1, axis=1))[0] == (0, -1)


def test_fourier_mix_lambda_zero_is_the_crop_and_a_pool_lends_its_colour():
    img, ref = _crop(4), np.full((64, 64, 3), (230, 20, 20), np.uint8)
    assert np.abs(fourier_mix(img, _rect(), 0.0, 0.1).astype(int) - img).max() <= 1
    t = FourierMix(refs=[ref], p=1.0)  # resized to the crop's side
    m0 = img.reshape(-1, 3).mean(axis=0)
    for o in _fired(t, img, range(20)):
        m = o.reshape(-1, 3).mean(axis=0)
        assert m[0] >= m0[0] - 1 and m[1] <= m0[1] + 1  # the mean colour moves towards the pool's
    d = DomainAugment(refs=[ref])
    assert np.array_equal(d(img, 11), d(img, 11))


def test_fbm_reference_is_an_image_drawn_from_the_seed():
    a = fbm_field(np.random.default_rng(5), 128, 128)
    b = fbm_field(np.random.default_rng(5), 128, 128)
    assert a.shape == (128, 128, 3) and np.array_equal(a, b)
    assert a.min() >= 0 and a.max() <= 255 and a.std() > 1


def test_the_texture_axes_leave_the_older_axes_draws_alone():
    # each axis's seed slot is fixed when it is added: with the texture axes off, a seed draws what
    # the eleven albumentations axes drew before there were any
    assert sorted(SEED_SLOTS) == sorted(AXES) and len(SEED_SLOTS) == len(AXES)
    assert SEED_SLOTS[-2:] == ("RandConv", "FourierMix")
    d, img = DomainAugment(), _crop(5)
    d._t.transforms[0].p = d._t.transforms[1].p = 0.0
    old = A.Compose(compose().transforms[2:], seed=0)  # the pipeline as it was
    for s in range(15):
        for tr, w in zip(old.transforms, np.random.SeedSequence(s).generate_state(11), strict=True):
            tr.set_random_seed(int(w))
        assert np.array_equal(d(img, s), old(image=img)["image"])
