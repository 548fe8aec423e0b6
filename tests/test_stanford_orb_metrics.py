"""Stanford-ORB's PSNR-H and PSNR-L (nefii.evaluate.stanford_orb) in closed form."""
from __future__ import annotations

import math

import numpy as np
import pytest

from nefii.evaluate.stanford_orb import (box_downsample, channel_scale, erode, relight_scores,
                                         scale_invariant_psnr)


def srgb(x: float) -> float:
    """IEC 61966-2-1 encoding of one value in [0, 1], written out here."""
    return 12.92 * x if x <= 0.0031308 else 1.055 * x ** (1 / 2.4) - 0.055


def psnr(mse: float) -> float:
    return -10.0 * math.log10(mse)


G0, A, B = 0.6, 1.0, 1.5
"""truth 0.6 in every channel; the prediction alternates A and B (a checkerboard): the least-squares scale
is ``s = G0 (A + B) / (A^2 + B^2)``, leaving errors ``G0 B (A - B) / (A^2 + B^2)`` and ``G0 A (B - A) / (...)``,
so ``MSE = G0^2 (A - B)^2 / (2 (A^2 + B^2)) = G0^2 / 26`` before clipping and encoding."""


def checkerboard(n: int) -> tuple[np.ndarray, np.ndarray]:
    ij = np.add.outer(np.arange(n), np.arange(n)) % 2
    pred = np.where(ij == 0, A, B)[..., None].repeat(3, -1)
    return pred, np.full((n, n, 3), G0)


def known_h() -> float:
    """PSNR-H: the brightness normalisation multiplies both by ``srgb(G0) / G0``, so the truth is ``srgb(G0)``."""
    return psnr(srgb(G0) ** 2 * (A - B) ** 2 / (2 * (A * A + B * B)))


def known_l() -> float:
    s = G0 * (A + B) / (A * A + B * B)
    return psnr(((srgb(s * A) - srgb(G0)) ** 2 + (srgb(s * B) - srgb(G0)) ** 2) / 2)


def test_erosion_by_a_five_pixel_square_keeps_the_border():
    m = np.zeros((9, 9), bool)
    m[1:8, 1:8] = True
    want = np.zeros((9, 9), bool)
    want[3:6, 3:6] = True
    assert np.array_equal(erode(m), want)
    assert erode(np.ones((4, 6), bool)).all()           # outside the image counts as inside


def test_scale_per_channel_is_least_squares_and_black_channels_take_the_mean():
    rng = np.random.default_rng(0)
    p = rng.uniform(0.1, 1.0, (5, 5, 3))
    p[..., 2] = 0.0
    g = p * [2.0, 0.5, 1.0] + [0.0, 0.0, 0.3]
    mask = np.ones((5, 5), bool)
    assert np.allclose(channel_scale(p, g, mask), [2.0, 0.5, 0.3])


def test_the_truth_times_a_constant_per_channel_scores_infinite():
    rng = np.random.default_rng(1)
    gt = rng.uniform(0.05, 0.9, (12, 12, 3))
    mask = np.ones((12, 12), bool)
    for hdr in (True, False):
        assert scale_invariant_psnr(gt * [0.3, 2.0, 0.7], gt, mask, hdr=hdr) > 100.0


def test_a_known_error_gives_a_known_psnr():
    """(sRGB is encoded in float32, as nefii encodes it: agreement to 1e-5 dB.)"""
    pred, gt = checkerboard(8)
    mask = np.ones((8, 8), bool)
    floor_h, floor_l = psnr((0.5 - srgb(G0)) ** 2), psnr((0.5 - srgb(G0)) ** 2)
    assert known_h() > floor_h + 3 and known_l() > floor_l + 3       # the floor does not decide
    assert scale_invariant_psnr(pred, gt, mask, hdr=True) == pytest.approx(known_h(), abs=1e-5)
    assert scale_invariant_psnr(pred, gt, mask, hdr=False) == pytest.approx(known_l(), abs=1e-5)
    assert relight_scores(pred, gt, mask) == pytest.approx({"psnr_h": known_h(), "psnr_l": known_l()}, abs=1e-5)


def test_the_mse_is_over_the_whole_image_and_the_mask_is_eroded():
    """The same object in a 32 x 32 frame: only its eroded 12 x 12 counts, divided by all 1024 pixels."""
    pred, gt = np.zeros((32, 32, 3)), np.zeros((32, 32, 3))
    mask = np.zeros((32, 32), bool)
    mask[8:24, 8:24] = True
    gt[8:24, 8:24], pred[8:24, 8:24] = G0, 7.0                 # a rim the erosion removes
    pred[10:22, 10:22] = checkerboard(12)[0]
    gain = 10 * math.log10(1024 / 144)
    assert scale_invariant_psnr(pred, gt, mask, hdr=True) == pytest.approx(known_h() + gain, abs=1e-5)
    assert scale_invariant_psnr(pred, gt, mask, hdr=False) == pytest.approx(known_l() + gain, abs=1e-5)


def test_a_black_prediction_scores_the_floor_of_a_uniform_half():
    gt = np.full((6, 6, 3), G0)
    mask = np.ones((6, 6), bool)
    assert scale_invariant_psnr(np.zeros_like(gt), gt, mask, hdr=True) == pytest.approx(psnr((0.5 - srgb(G0)) ** 2))
    assert scale_invariant_psnr(np.zeros_like(gt), gt, mask, hdr=False) == pytest.approx(psnr((0.5 - srgb(G0)) ** 2))


def test_values_above_the_clip_are_not_told_apart():
    """A truth of 20 everywhere (normalisation factor 1) and a prediction of 20 with some pixels at 30: after
    the scale both sides are above 4 (H) and 1 (L) everywhere, so they clip to the same image."""
    gt = np.full((8, 8, 3), 20.0)
    pred = gt.copy()
    pred[2:4, 2:4] = 30.0
    mask = np.ones((8, 8), bool)
    for hdr in (True, False):
        assert scale_invariant_psnr(pred, gt, mask, hdr=hdr) == math.inf


def test_empty_eroded_mask_is_nan_and_large_images_are_scored_at_512():
    mask = np.zeros((8, 8), bool)
    mask[2:5, 2:5] = True
    assert math.isnan(scale_invariant_psnr(np.ones((8, 8, 3)), np.ones((8, 8, 3)), mask, hdr=True))
    rng = np.random.default_rng(2)
    gt = rng.uniform(0.0, 1.0, (1024, 1024, 3))
    pred = gt * rng.uniform(0.8, 1.2, (1024, 1024, 1))
    big = np.zeros((1024, 1024), bool)
    big[100:900, 200:800] = True
    got = relight_scores(pred, gt, big)
    small = box_downsample(big.astype(float), 2) > 0.5
    want = {"psnr_h": scale_invariant_psnr(box_downsample(pred, 2), box_downsample(gt, 2), small, hdr=True),
            "psnr_l": scale_invariant_psnr(box_downsample(pred, 2), box_downsample(gt, 2), small, hdr=False)}
    assert got == pytest.approx(want) and got["psnr_h"] != pytest.approx(
        scale_invariant_psnr(pred, gt, big, hdr=True))
