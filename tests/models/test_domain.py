"""Domain randomisation of the crops (oibar_models.domain): seeded, every axis drawn, labels
untouched, and off unless a config asks (the crops of every model trained so far unchanged)."""

from dataclasses import replace

import numpy as np
import pytest

from oibar_models.domain import AXES, DomainAugment, compose
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
