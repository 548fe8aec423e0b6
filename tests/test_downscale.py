"""Large photographs averaged down at load time: pixels, masks, clipped pixels and intrinsics agree."""
from __future__ import annotations

import dataclasses

import pytest
import torch

from data_fixtures import make_truth, write_nefii, write_physg
from nefii.camera import pixel_rays
from nefii.data import load_scene
from nefii.data.downscale import downscaled, factor_for, training_images


def _scene(tmp_path, n=3, size=(24, 30)):
    """A loaded scene (8-bit PNGs with masks) whose images are replaced by each pixel's centre ``x`` in the
    camera's image plane (x = (j + 0.5 - cx) / fx): linear in ``j``, so its block mean is the block centre's."""
    write_physg(tmp_path / "s", make_truth(n))
    scene = load_scene(tmp_path / "s")
    h, w = size
    K = scene.cameras.K.clone()
    K[:, 0, 2], K[:, 1, 2] = w / 2 + 0.3, h / 2 - 0.2
    cams = dataclasses.replace(scene.cameras, K=K, height=h, width=w)
    x = (torch.arange(w, dtype=torch.float64) + 0.5 - K[:, 0, 2, None]) / K[:, 0, 0, None]     # (N, W)
    images = x[:, None, :, None].expand(n, h, w, 3).float().contiguous()
    g = torch.Generator().manual_seed(0)
    masks = torch.rand(n, h, w, generator=g) < 0.5
    clipped = torch.rand(n, h, w, generator=g) < 0.02
    return dataclasses.replace(scene, images=images, masks=masks, clipped=clipped, cameras=cams,
                               ground_truth=None, relit=())


def test_factor_is_the_smallest_that_fits():
    assert factor_for(3024, 4032, 512) == 8
    assert factor_for(512, 512, 512) == 1
    assert factor_for(513, 100, 512) == 2
    assert factor_for(4000, 3000, 0) == 1


@pytest.mark.parametrize("max_side", [15, 10, 8])
def test_pixels_and_rays_stay_together(tmp_path, max_side):
    scene = _scene(tmp_path)
    small, f = downscaled(scene, max_side)
    assert f == factor_for(24, 30, max_side) and f > 1
    h, w = 24 // f, 30 // f
    assert (small.height, small.width) == (h, w) and small.images.shape == (3, h, w, 3)
    # the image holds each pixel's x in the image plane: averaged over a block it must be where the
    # small camera's ray through that pixel's centre points, which tests K's convention exactly
    for v in range(3):
        _, d = pixel_rays(small.cameras.c2w[v], small.cameras.K[v], h, w)
        d_cam = d @ small.cameras.c2w[v, :3, :3]
        x = d_cam[..., 0] / d_cam[..., 2]
        torch.testing.assert_close(small.images[v, ..., 0].double(), x, atol=1e-5, rtol=0)
    block = scene.masks[:, :h * f, :w * f].reshape(3, h, f, w, f).float().mean((2, 4))
    assert torch.equal(small.masks, block >= 0.5)
    assert torch.equal(small.clipped, scene.clipped[:, :h * f, :w * f].reshape(3, h, f, w, f).any(4).any(2))
    assert torch.equal(small.cameras.c2w, scene.cameras.c2w)


def test_small_images_and_scoring_data_are_left_alone(tmp_path):
    scene = _scene(tmp_path)
    assert downscaled(scene, 30)[0] is scene
    assert training_images(scene, 30) == (scene, None)
    small, line = training_images(scene, 15)
    assert small.width == 15 and line == "images averaged down 2x: 30x24 -> 15x12 (max_image_side 15)"
    write_nefii(tmp_path / "t", make_truth(2), "test")
    with_truth = load_scene(tmp_path / "t", "test")
    assert with_truth.ground_truth is not None
    assert downscaled(with_truth, 4)[0] is with_truth
