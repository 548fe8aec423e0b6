"""Table 1 metrics: PSNR/SSIM conventions, masked variants, median albedo alignment, both protocols."""
import math

import numpy as np
import pytest
from skimage.metrics import structural_similarity

from nefii.evaluate.metrics import median_scale, mse, psnr, ssim
from nefii.evaluate.table1 import METRIC_KEYS, ViewArrays, mean_scores, view_scores


def test_psnr_and_mse():
    a = np.zeros((4, 4, 3))
    b = np.full((4, 4, 3), 0.1)
    assert psnr(a, b) == pytest.approx(20.0)
    mask = np.zeros((4, 4), bool)
    mask[0, 0] = True
    b2 = b.copy()
    b2[~mask] = 0.5
    assert psnr(a, b2, mask) == pytest.approx(20.0) and psnr(a, b2) < 20.0
    assert math.isnan(psnr(a, b, np.zeros((4, 4), bool))) and math.isinf(psnr(a, a))
    assert mse(a, b2, mask) == pytest.approx(0.01)


def test_ssim_is_the_gaussian_nerf_convention():
    rng = np.random.default_rng(0)
    a = rng.uniform(size=(32, 32, 3))
    b = np.clip(a + rng.normal(0, 0.05, a.shape), 0, 1)
    ref = structural_similarity(a, b, gaussian_weights=True, sigma=1.5, use_sample_covariance=False, data_range=1.0,
                                channel_axis=-1)
    assert ssim(a, b) == pytest.approx(ref, abs=1e-9)
    assert ssim(a, a) == pytest.approx(1.0)


def test_median_scale_recovers_a_per_channel_scale():
    rng = np.random.default_rng(1)
    gt = rng.uniform(0.1, 0.9, (16, 16, 3))
    mask = rng.uniform(size=(16, 16)) > 0.3
    pred = gt / np.array([2.0, 0.5, 1.25])
    pred[~mask] = 123.0  # outside the mask nothing counts
    assert np.allclose(median_scale(pred, gt, mask), [2.0, 0.5, 1.25], rtol=1e-5)


def test_view_scores_align_albedo_and_fill_both_protocols():
    rng = np.random.default_rng(2)
    H = W = 24
    mask = np.zeros((H, W), bool)
    mask[4:20, 4:20] = True
    gt = ViewArrays(rgb=rng.uniform(size=(H, W, 3)), albedo=rng.uniform(0.1, 0.9, (H, W, 3)),
                    roughness=rng.uniform(size=(H, W)), specular=rng.uniform(size=(H, W, 3)) * 0.1)
    pred = ViewArrays(rgb=gt.rgb, albedo=gt.albedo * 0.5, roughness=gt.roughness + 0.1, specular=gt.specular)
    blocks, scale = view_scores(pred, gt, mask)
    assert np.allclose(scale, 2.0)
    for protocol in ("masked", "whole_image"):
        b = blocks[protocol]
        assert set(b) == set(METRIC_KEYS)
        assert math.isinf(b["albedo_psnr"]) and math.isinf(b["rgb_psnr"])  # aligned albedo is exact
        assert b["albedo_lpips"] is None
    assert blocks["masked"]["roughness_mse"] == pytest.approx(0.01)
    # the official protocol dilutes the error by the white background
    assert blocks["whole_image"]["roughness_mse"] == pytest.approx(0.01 * mask.mean())
    mean = mean_scores([blocks, blocks])
    assert mean["masked"]["roughness_mse"] == pytest.approx(0.01)
