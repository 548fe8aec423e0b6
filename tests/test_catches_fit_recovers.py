"""A fit must move towards the materials of a scene whose materials are known, and the demo must
reach a useful albedo (issue 26, item 7).

The scene of :mod:`fit_fixtures` (rendered by nefii's own estimator, so the fit's model can explain
it exactly) has two albedos: red (0.7, 0.2, 0.15) where x > 0 and blue (0.3, 0.5, 0.7) elsewhere.
Albedo is recovered only up to a per-channel scale shared with the light, so the check is on what a
scale cannot change: the red/blue ratio per channel, (2.33, 0.40, 0.21), far from the untrained
model's (1, 1, 1). Measured on 2026-11-25 over 10 tiny-preset fits (80 to 240 steps, seeds 0 to 2,
16 and 24 px): the ratios reached (1.6-2.2, 0.46-0.63, 0.27-0.42), 50 to 90 % of the way in log
space, and the masked albedo PSNR 19.5-25.5 dB (untrained: 15.6 dB). At this resolution (16 px) roughness (0.3 ball,
0.8 slab) is not recovered, so it is not checked; more steps do not help (240 steps: 19.5 dB).
"""
import json
import math

import numpy as np
import pytest
from scipy.ndimage import binary_erosion

from catches_fixtures import fitted_tiny_run
from nefii.cli.main import main
from nefii.io.exr import read_exr

TRUE_RATIO = np.array([0.7, 0.2, 0.15]) / np.array([0.3, 0.5, 0.7])


def test_a_tiny_fit_moves_the_albedo_towards_the_known_materials(tmp_path):
    scene, run = fitted_tiny_run(tmp_path, steps=80, overrides=("lr=0.02",))
    assert main(["eval", str(run), "--spp", "8", "--quiet"]) == 0
    metrics = json.loads((run / "eval" / "metrics.json").read_text())
    assert metrics["masked"]["albedo_psnr"] > 18.0, metrics["masked"]
    for v in (0, 1):
        gt = read_exr(scene / "test" / f"r_{v}_albedo.exr")
        pred = read_exr(run / "eval" / f"{v}_albedo.exr")
        red, blue = binary_erosion(gt[..., 0] > 0.6), binary_erosion(gt[..., 2] > 0.6)  # away from the seam
        assert red.sum() >= 3 and blue.sum() >= 3
        ratio = pred[red].mean(0) / pred[blue].mean(0)
        progress = np.log(ratio) / np.log(TRUE_RATIO)        # 0: untrained, 1: the true ratio
        assert np.all(progress > 0.35) and np.all(progress < 1.5), (v, ratio, progress)


@pytest.mark.slow
@pytest.mark.timeout(3 * 3600)
def test_the_demo_runs_end_to_end_and_recovers_a_useful_albedo(tmp_path):
    """``nefii demo`` as a user runs it: synthesis (Mitsuba), a ``cpu``-preset fit, eval. On the bowl a
    constant albedo already scores 20.56 dB (benchmarks/results/peers.md) and nefii 22.7 dB, so the
    bar is set between them."""
    out = tmp_path / "demo"
    assert main(["demo", "--out", str(out)]) == 0
    metrics = json.loads((out / "run" / "eval" / "metrics.json").read_text())
    assert len(metrics["views"]) == 8
    psnr = metrics["masked"]["albedo_psnr"]
    assert math.isfinite(psnr) and psnr > 21.0, metrics["masked"]
    assert metrics["masked"]["rgb_psnr"] > 20.0, metrics["masked"]
