"""Eval's pixels are box-filtered like a renderer's ground truth: stripes finer than a pixel average out."""
import numpy as np
import torch
from torch import nn

from nefii.camera import intrinsics_from_fov, look_at
from nefii.data.scene import Cameras
from nefii.evaluate.render_views import render_view, subpixel_grid
from nefii.fit.build import build_model
from nefii.fit.config import resolve_config
from nefii.raycast import MeshGeometry
from nefii.render.brdf import Material


class Stripes(nn.Module):
    """Albedo 1 where ``frac(x / period) < 0.5``, else 0 (grey-free), roughness 0.5."""

    def __init__(self, period: float) -> None:
        super().__init__()
        self.period = period
        self.dummy = nn.Parameter(torch.zeros(1))

    def forward(self, x, normal=None, roughness_override=None):
        on = (torch.remainder(x[..., 0] / self.period, 1.0) < 0.5).float()
        return Material(on.unsqueeze(-1).expand(*on.shape, 3), torch.full_like(on, 0.5))


def plane_view(res: int, eye: tuple[float, float, float], fov_deg: float):
    """A plane at z = 0 seen from ``eye`` by one ``res`` x ``res`` camera, and a `tiny` model over it."""
    plane = MeshGeometry(np.array([[-2, -2, 0], [2, -2, 0], [2, 2, 0], [-2, 2, 0.0]]), np.array([[0, 1, 2], [0, 2, 3]]))
    c2w = look_at(torch.tensor(eye, dtype=torch.float64), torch.zeros(3, dtype=torch.float64),
                  torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64))
    cams = Cameras(intrinsics_from_fov(np.radians(fov_deg), res, res).unsqueeze(0), c2w.unsqueeze(0), res, res)
    box = tuple(torch.from_numpy(b.copy()) for b in plane.bounds)
    return plane, cams, build_model(resolve_config("tiny", []), box)


def test_eval_averages_the_material_over_each_pixel():
    res = 16
    plane, cams, model = plane_view(res, (0.0, 0.0, 5.0), 20.0)
    pixel_width = 2 * 5.0 * np.tan(np.radians(10.0)) / res                 # on the plane, about 0.11
    model.material = Stripes(period=pixel_width / 5.3)                     # 5.3 stripes per pixel
    assert subpixel_grid(64) == 4 and subpixel_grid(1) == 1
    filtered = render_view(model, plane, cams, 0, 64, torch.Generator().manual_seed(0)).albedo[..., 0]
    # a point sample would be 0 or 1; the pixel average of 5.3 stripes is near their duty cycle 0.5
    assert (filtered - 0.5).abs().max() <= 0.3 and (filtered - 0.5).abs().mean() < 0.12
    assert abs(float(filtered.mean()) - 0.5) < 0.03


def test_the_material_layers_do_not_depend_on_the_sample_count():
    """At 1 spp the colour is one ray through each pixel's centre, but the albedo, roughness, normal and mask
    are still the 4 x 4 sub-pixel average: an eval at a low ``--spp`` scores the same material (it scored a fit
    0.9 dB lower when the material shared the colour's rays)."""
    res = 16
    plane, cams, model = plane_view(res, (0.3, -0.4, 5.0), 20.0)
    model.material = Stripes(period=2 * 5.0 * np.tan(np.radians(10.0)) / res / 5.3)
    low, high = (render_view(model, plane, cams, 0, spp, torch.Generator().manual_seed(0)) for spp in (1, 64))
    assert (low.albedo[..., 0] - 0.5).abs().mean() < 0.15               # filtered: a point sample is 0 or 1
    for name in ("albedo", "roughness", "normal", "cache", "mask"):
        assert torch.equal(getattr(low, name), getattr(high, name)), name
    assert not torch.equal(low.rgb, high.rgb)                            # the colour is still the 1-spp estimate


def test_render_view_is_the_same_for_any_number_of_worker_threads():
    """Chunks rendered by threads draw from generators of their own and are summed in order: one worker and
    three give the same image to the bit, and a different seed gives a different one."""
    plane, cams, model = plane_view(12, (1.0, -2.0, 5.0), 30.0)

    def render(workers: int, seed: int = 0):
        return render_view(model, plane, cams, 0, 8, torch.Generator().manual_seed(seed), chunk=40, workers=workers)

    one, three = render(1), render(3)
    assert one.mask.sum() > 100                                            # several chunks of 40 rays
    for name in ("rgb", "specular", "albedo", "roughness", "cache"):
        assert torch.equal(getattr(one, name), getattr(three, name)), name
    assert not torch.equal(one.rgb, render(3, seed=1).rgb)
