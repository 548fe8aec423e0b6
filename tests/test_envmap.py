"""Env-map light: piecewise-constant 2D sampling against its pdf, lookup and the mapping."""
import math

import numpy as np
import pytest
import scipy.stats
import torch

from chi2 import pooled_chi2
from nefii.render.envmap import build_envmap_distribution, envmap_lookup, pdf_envmap, sample_envmap
from nefii.render.equirect import direction_to_uv, pixel_directions, pixel_solid_angles

H, W, SUB = 8, 16, 3


def make_map():
    g = torch.Generator().manual_seed(0)
    img = torch.rand(H, W, 3, generator=g, dtype=torch.float64) ** 3 * 5
    img[2, 5] = 400.0  # a sun
    img[6, :] = 0.0    # a black row: reachable only through the floor
    return img


def uv_histogram(w: torch.Tensor) -> np.ndarray:
    u, v = direction_to_uv(w)
    i = (v * H * SUB).long().clamp(0, H * SUB - 1)
    j = (u * W * SUB).long().clamp(0, W * SUB - 1)
    return torch.bincount(i * W * SUB + j, minlength=H * W * SUB * SUB).double().numpy()


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_envmap_sampling_chi2_in_pixel_space(seed):
    """Sub-pixel bins: the pixel choice follows p_uv and positions inside a pixel are uniform."""
    dist = build_envmap_distribution(make_map())
    n = 400_000
    u = torch.rand(n, 2, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)
    observed = uv_histogram(sample_envmap(dist, u))
    expected = (dist.p_uv.repeat_interleave(SUB, 0).repeat_interleave(SUB, 1) / (H * W * SUB * SUB)).flatten()
    stat, dof, failure = pooled_chi2(observed, n * expected.numpy())
    assert failure is None
    assert scipy.stats.chi2.sf(stat, dof) > 0.01 / 3


def test_envmap_pdf_integrates_to_one_over_solid_angle():
    dist = build_envmap_distribution(make_map())
    f = 8  # a grid finer than the map's pixels
    d = pixel_directions(H * f, W * f, dtype=torch.float64)
    dw = pixel_solid_angles(H * f, W * f, dtype=torch.float64)
    assert float((pdf_envmap(dist, d) * dw).sum()) == pytest.approx(1.0, abs=2e-3)


def test_envmap_estimator_is_unbiased_and_a_wrong_pdf_is_caught():
    img = make_map()
    dist = build_envmap_distribution(img)
    truth = (img * pixel_solid_angles(H, W, dtype=torch.float64).unsqueeze(-1)).sum((0, 1))
    n = 400_000
    w = sample_envmap(dist, torch.rand(n, 2, generator=torch.Generator().manual_seed(7), dtype=torch.float64))
    est = envmap_lookup(img, w) / pdf_envmap(dist, w).unsqueeze(-1)
    mean, se = est.mean(0), est.std(0) / math.sqrt(n)
    assert ((mean - truth).abs() < 4 * se).all(), (mean, truth, se)
    # the Jacobian matters: without sin(theta) the estimate is far off
    u, v = direction_to_uv(w)
    wrong = pdf_envmap(dist, w) * torch.sin(v * math.pi)
    bad = (envmap_lookup(img, w) / wrong.unsqueeze(-1)).mean(0)
    assert ((bad - truth).abs() > 20 * se).all()


def test_lookup_follows_the_documented_mapping():
    img = torch.zeros(H, W, 3)
    img[H // 2 - 1, W // 2] = 1.0   # just above the horizon, u just past 0.5: +X
    img[0, 3 * W // 4] = 2.0        # top row, u = 0.75: -Y near the zenith
    assert envmap_lookup(img, torch.tensor([[1.0, 0.0, 0.05]]))[0, 0] == 1.0
    assert envmap_lookup(img, torch.tensor([[0.0, -0.02, 1.0]]))[0, 0] == 2.0
    assert envmap_lookup(img, torch.tensor([[0.0, 0.02, 1.0]]))[0, 0] == 0.0
