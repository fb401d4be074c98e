"""The float64 metric references against closed forms."""

import math

import numpy as np
import pytest

from c4g.raster.metrics import psnr, ssim, window


def test_identical_images_give_infinite_psnr_and_unit_ssim():
    a = np.random.default_rng(0).uniform(size=(20, 24, 3))
    assert psnr(a, a) == math.inf
    assert ssim(a, a) == pytest.approx(1.0, abs=1e-12)


def test_uniform_error_gives_its_psnr():
    a = np.full((16, 16, 3), 0.4)
    assert psnr(a, a + 0.1) == pytest.approx(20.0)
    assert psnr(a, a + 0.01) == pytest.approx(40.0)


def test_flat_images_score_the_luminance_term():
    x, y, c1 = 0.3, 0.6, 1e-4
    assert ssim(np.full((15, 20, 3), x), np.full((15, 20, 3), y)) == pytest.approx((2 * x * y + c1) / (x * x + y * y + c1))


def test_window_is_normalised_gaussian():
    k = window()
    assert k.shape == (11, 11) and k.sum() == pytest.approx(1.0)
    assert k[5, 5] / k[5, 6] == pytest.approx(math.exp(1 / 4.5))


def test_a_mask_restricts_both_metrics():
    rng = np.random.default_rng(1)
    a = rng.uniform(size=(30, 30, 3))
    b = a.copy()
    b[:, :10] = rng.uniform(size=(30, 10, 3))
    mask = np.zeros((30, 30), bool)
    mask[:, 20:] = True  # windows centred at x >= 20 reach down to x = 15: untouched
    assert psnr(a, b, mask) == math.inf
    assert ssim(a, b, mask) == pytest.approx(1.0)
    assert ssim(a, b) < 0.9
