"""A background of one colour (images composited over white or black, as datasets made for NeRF ship them) is a
backdrop, not the environment: the fit leaves it out of the light's fit; a background that varies stays in."""
from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from fit_fixtures import write_rendered_scene

from nefii.fit.backdrop import backdrop_colour
from nefii.fit.config import resolve_config
from nefii.fit.session import prepare_fit
from nefii.io.exr import read_exr, write_exr


def test_one_colour_is_a_backdrop_and_a_sky_is_not():
    g = torch.Generator().manual_seed(0)
    white = 1.0 + 0.004 * torch.randn(10000, 3, generator=g)
    assert torch.allclose(backdrop_colour(white), torch.ones(3), atol=1e-3)
    black = (torch.randint(0, 3, (10000, 3), generator=g).float() / 255.0) ** 2.2      # 8-bit near-black
    assert backdrop_colour(black) is not None
    sky = torch.linspace(0.2, 1.5, 10000)[:, None] * torch.tensor([0.6, 0.8, 1.0])    # a gradient
    assert backdrop_colour(sky) is None
    mostly = white.clone()
    mostly[:800] = 0.3                                                                  # 8% another colour
    assert backdrop_colour(mostly) is None
    assert backdrop_colour(torch.zeros(0, 3)) is None


def composited(scene: Path, out: Path, background) -> Path:
    """``scene`` with its training images composited over ``background(H, W) -> (H, W, 3)``, alpha dropped."""
    shutil.copytree(scene, out)
    for f in (out / "train").glob("r_*.exr"):
        img = read_exr(f)
        a = img[..., 3:4]
        write_exr(f, np.ascontiguousarray(img[..., :3] + (1 - a) * background(*img.shape[:2])))
    return out


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return write_rendered_scene(tmp_path_factory.mktemp("scene"), res=16, n_train=6, n_test=2)


def test_the_fit_leaves_a_white_backdrop_out_and_keeps_a_varying_background(scene, tmp_path):
    lines: list[str] = []
    white = composited(scene, tmp_path / "white", lambda h, w: np.ones((h, w, 3), np.float32))
    session = prepare_fit(resolve_config("tiny", []), white, say=lines.append)
    assert len(session.pixels.bg_dirs) == 0 and len(session.pixels.points) > 0
    assert any("backdrop" in line for line in lines)
    # the edge pixels mix the object with the backdrop, which the fit does not render: dropped
    assert not bool(session.pixels.edge.any()) and not any("on the silhouette" in line for line in lines)

    def ramp(h, w):
        return np.broadcast_to(np.linspace(0.1, 2.0, w, dtype=np.float32)[None, :, None], (h, w, 3)).copy()

    lines.clear()
    varying = prepare_fit(resolve_config("tiny", []), composited(scene, tmp_path / "ramp", ramp), say=lines.append)
    assert len(varying.pixels.bg_dirs) > 0 and not any("backdrop" in line for line in lines)
    edges = int(varying.pixels.edge.sum())
    assert edges > 0 and any(f"({edges} on the silhouette" in line for line in lines)
    # the light solve reads the pixels fitted as object alone
    assert torch.equal(varying.trainer.solid_pixels, (~varying.pixels.edge).nonzero()[:, 0])
    assert len(varying.trainer.solid_pixels) == len(varying.pixels.points) - edges
