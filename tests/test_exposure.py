"""Per-view exposure: a learned RGB gain per training view finds a view shot one stop brighter."""
from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from fit_fixtures import write_rendered_scene
from nefii.cli.main import main
from nefii.fit.exposure import ViewGains
from nefii.io.exr import read_exr, write_exr


def test_view_gains_are_relative_and_start_at_one():
    g = ViewGains(4)
    torch.testing.assert_close(g(torch.tensor([0, 3, 1])), torch.ones(3, 3))
    with torch.no_grad():
        g.log_gain.fill_(0.5)  # every view brighter is no change: the scale is the light's
    torch.testing.assert_close(g.all(), torch.ones(4, 3))
    assert float(g.prior().detach()) == 0.0
    with torch.no_grad():
        g.log_gain[1] += float(np.log(2.0))
    got = g.all()
    torch.testing.assert_close(got[1] / got[0], torch.full((3,), 2.0))
    torch.testing.assert_close(got.log().mean(0), torch.zeros(3), atol=1e-6, rtol=0)
    assert float(g.prior().detach()) > 0
    with pytest.raises(ValueError):
        ViewGains(0)


def test_view_gains_start_from_metered_exposures_and_are_pulled_back_there():
    metered = torch.tensor([1 / 100, 1 / 50, 1 / 200, 1 / 100], dtype=torch.float64)
    g = ViewGains(4, metered)
    want = (metered / metered.log().mean().exp()).float()[:, None].expand(4, 3)
    torch.testing.assert_close(g.all(), want)           # relative to their geometric mean
    assert float(g.prior().detach()) == 0.0             # the prior's centre is the metered start
    with torch.no_grad():
        g.log_gain[2] += 0.3
    assert float(g.prior().detach()) > 0
    assert "expected" not in g.state_dict()             # from the data, recomputed on resume
    for bad in (torch.ones(3), torch.tensor([1.0, 0.0, 1.0, 1.0])):
        with pytest.raises(ValueError):
            ViewGains(4, bad)


def test_a_view_at_plus_one_ev_gets_a_gain_of_two(tmp_path):
    """Twelve views, one of them one stop brighter: its gain is twice the others' (their median), within 5%
    averaged over the channels and 10% in each (a tiny fit's colour is not exact: where a view sees mostly the
    red half of the ball, its white balance and that half's albedo trade a little). 32 pixels a side: at 24 the
    ratio's mean came out 5.2% low on one machine and within 5% on another (a tiny fit's colour moves with the
    order of its sums); at 32, 0.8% high and 2.1% low at seeds 0 and 1 (2026-12-02). Without the light solve:
    on a 24-pixel scene a solve every 100 steps sets the bright view's gain 4-6% low (ratio / 2 of
    0.936-0.962 over three seeds and at 3000 steps, against 0.979-0.982 without it; docs/experiments.md,
    2026-11-27, third session), a bias not yet explained."""
    scene = write_rendered_scene(tmp_path / "scene", res=32, n_train=12, n_test=1)
    bright = scene / "train" / "r_1.exr"
    img = read_exr(bright)
    img[..., :3] *= 2.0  # premultiplied RGBA: one stop brighter, same coverage
    write_exr(bright, img)
    run = tmp_path / "run"
    assert main(["fit", str(scene), "--out", str(run), "--preset", "tiny", "--quiet",
                 "--set", "steps=1500", "--set", "exposure=per_view", "--set", "threads=1",
                 "--set", "light_solve_every=0"]) == 0
    gains = json.loads((run / "exposure.json").read_text())["gains"]
    assert len(gains) == 12
    g = np.array([gains[f"train/r_{k}.exr"] for k in range(12)])
    np.testing.assert_allclose(np.exp(np.log(g).mean(0)), 1.0, atol=2e-4)  # geometric mean 1 (rounded)
    others = np.median(np.delete(g, 1, 0), axis=0)
    ratio = g[1] / others
    assert abs(ratio.mean() / 2.0 - 1.0) < 0.05, ratio
    np.testing.assert_allclose(ratio, 2.0, rtol=0.10)
    np.testing.assert_allclose(np.delete(g, 1, 0) / others, 1.0, rtol=0.10)
