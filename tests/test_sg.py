"""Spherical Gaussians (nefii.render.sg) and the equirectangular mapping they are rendered through.

The equirect convention tested here is the one documented in src/nefii/render/equirect.py and
docs/design.md: ``u = 0.5 - phi / 2 pi (mod 1)``, ``v = theta / pi``, +X at u = 0.5, +Y at
u = 0.25, -Y at u = 0.75, -X at the seam, +Z on row 0.
"""
from __future__ import annotations

import math

import pytest
import torch

from autograd_graph import graph_names
from quadrature import DTYPE, integrate_sphere
from nefii.render.equirect import (direction_to_pixel, direction_to_uv, pixel_directions, pixel_solid_angles,
                                   uv_to_direction)
from nefii.render.sg import (SGMixture, fibonacci_sphere, sg_detach_sharper, sg_energy, sg_eval, sg_integral, sg_lobes,
                             sg_to_equirect)


def tensor(*values: float) -> torch.Tensor:
    return torch.tensor(values, dtype=DTYPE)


def unit(*values: float) -> torch.Tensor:
    v = tensor(*values)
    return v / v.norm()


def one_lobe(axis: torch.Tensor, sharpness: float, amplitude=(1.0, 1.0, 1.0)) -> SGMixture:
    return SGMixture(axis.reshape(1, 3), tensor(sharpness), tensor(*amplitude).reshape(1, 3))


# --------------------------------------------------------------------------- lobe integrals


@pytest.mark.parametrize("sharpness", (0.1, 1.0, 10.0, 100.0, 1000.0))
def test_sg_integral_matches_quadrature(sharpness: float) -> None:
    """``2 pi / lambda (1 - e^{-2 lambda})`` against a graded quadrature of ``sg_lobes`` about a tilted axis."""
    axis = unit(-0.4, 0.7, 0.2)
    sg = one_lobe(axis, sharpness)
    numeric = integrate_sphere(lambda w: sg_lobes(w, sg)[..., 0], axis, eps=1e-3 / sharpness)
    assert float(sg_integral(tensor(sharpness))) == pytest.approx(numeric, rel=1e-7)


def test_sg_integral_limits() -> None:
    """A flat lobe covers the sphere (4 pi); a sharp one tends to ``2 pi / lambda``; float32 keeps precision."""
    assert float(sg_integral(tensor(1e-9))) == pytest.approx(4.0 * math.pi, rel=1e-8)
    assert float(sg_integral(tensor(5e3))) == pytest.approx(2.0 * math.pi / 5e3, rel=1e-12)
    lam32 = torch.tensor([1e-6, 1e-3, 1.0, 3e3], dtype=torch.float32)
    torch.testing.assert_close(sg_integral(lam32).double(), sg_integral(lam32.double()), rtol=1e-6, atol=0.0)


def test_sg_energy_is_mean_abs_amplitude_times_integral() -> None:
    """``mu_bar_k = mean_rgb |mu_k| int G_k`` (Eq. 6), negative amplitudes counting by magnitude."""
    axes = torch.stack([unit(0.0, 0.0, 1.0), unit(1.0, 2.0, -0.5), unit(-0.3, 0.1, 0.4)])
    sharpness = tensor(0.5, 30.0, 400.0)
    amplitude = torch.stack([tensor(1.0, 2.0, 3.0), tensor(-4.0, 0.5, 0.0), tensor(10.0, -10.0, 10.0)])
    sg = SGMixture(axes, sharpness, amplitude)
    numeric = tensor(*(integrate_sphere(lambda w, k=k: sg_lobes(w, sg)[..., k], axes[k], eps=1e-3 / float(sharpness[k]))
                       for k in range(3)))
    want = tensor(2.0, 4.5 / 3.0, 10.0) * numeric
    torch.testing.assert_close(sg_energy(sg), want, rtol=1e-7, atol=0.0)


def test_sg_eval_is_the_sum_of_lobes() -> None:
    """``sum_k mu_k exp(lambda_k (w.xi_k - 1))``, written out, at random directions."""
    gen = torch.Generator().manual_seed(2)
    axes = torch.nn.functional.normalize(torch.randn(5, 3, generator=gen, dtype=DTYPE), dim=-1)
    sharpness = tensor(0.3, 3.0, 30.0, 300.0, 1000.0)
    amplitude = torch.rand(5, 3, generator=gen, dtype=DTYPE)
    w = torch.nn.functional.normalize(torch.randn(7, 11, 3, generator=gen, dtype=DTYPE), dim=-1)
    want = sum(amplitude[k] * torch.exp(sharpness[k] * ((w * axes[k]).sum(-1, keepdim=True) - 1.0)) for k in range(5))
    torch.testing.assert_close(sg_eval(w, SGMixture(axes, sharpness, amplitude)), want, rtol=1e-10, atol=1e-300)
    torch.testing.assert_close(sg_eval(axes[3], SGMixture(axes[3:4], sharpness[3:4], amplitude[3:4])), amplitude[3])


def test_sg_eval_with_gradient_is_the_sum_of_lobes_and_its_gradient_is_exact() -> None:
    """The lobes' gradient path (a hand-written backward): the written-out sum's value, gradients that match
    finite differences (gradcheck, float64) and autograd's through the plain product, with one lobe so sharp
    that most directions sit on the exponent's floor (no gradient there)."""
    gen = torch.Generator().manual_seed(5)
    axes = torch.nn.functional.normalize(torch.randn(6, 3, generator=gen, dtype=DTYPE), dim=-1)
    sharpness = tensor(0.3, 3.0, 30.0, 300.0, 1000.0, 5000.0)
    amplitude = torch.rand(6, 3, generator=gen, dtype=DTYPE)
    w = torch.nn.functional.normalize(torch.randn(4, 9, 3, generator=gen, dtype=DTYPE), dim=-1)
    w[0, 0] = axes[5]                                         # one direction inside the sharpest lobe
    params = [t.clone().requires_grad_() for t in (axes, sharpness, amplitude)]
    out = sg_eval(w, SGMixture(*params))
    assert "_SGRadianceBackward" in graph_names(out)
    want = sum(amplitude[k] * torch.exp(sharpness[k] * ((w * axes[k]).sum(-1, keepdim=True) - 1.0)) for k in range(6))
    torch.testing.assert_close(out.detach(), want, rtol=1e-10, atol=1e-300)
    assert torch.autograd.gradcheck(lambda a, s, m: sg_eval(w, SGMixture(a, s, m)), params)
    cot = torch.randn(out.shape, generator=gen, dtype=DTYPE)
    mine = torch.autograd.grad((out * cot).sum(), params)
    plain = sg_eval(w.clone().requires_grad_(), SGMixture(*params))   # a point gradient wanted: autograd's path
    assert plain.grad_fn is not None and "_SGRadianceBackward" not in graph_names(plain)
    for a, b in zip(mine, torch.autograd.grad((plain * cot).sum(), params)):
        torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-12)


# --------------------------------------------------------------------------- shapes


@pytest.mark.parametrize("axis, sharpness, amplitude", [
    ((4, 2), (4,), (4, 3)),
    ((4, 3), (4, 1), (4, 3)),
    ((4, 3), (4,), (4,)),
    ((4, 3), (5,), (4, 3)),
    ((4, 3), (4,), (3, 3)),
    ((4, 3), (4,), (4, 4)),
    ((3,), (1,), (1, 3)),
    ((2, 4, 3), (2, 4), (2, 4, 3)),
])
def test_sg_mixture_rejects_wrong_shapes(axis, sharpness, amplitude) -> None:
    with pytest.raises(ValueError, match="SGMixture wants"):
        SGMixture(torch.zeros(axis), torch.ones(sharpness), torch.ones(amplitude))


def test_sg_mixture_accepts_right_shapes() -> None:
    sg = SGMixture(torch.zeros(6, 3), torch.ones(6), torch.ones(6, 3))
    assert sg.num_lobes == 6


# --------------------------------------------------------------------------- equirect convention

KNOWN = [  # (direction, u, v) from the documented convention
    ((1.0, 0.0, 0.0), 0.5, 0.5),
    ((0.0, 1.0, 0.0), 0.25, 0.5),
    ((0.0, -1.0, 0.0), 0.75, 0.5),
    ((0.0, 0.0, 1.0), None, 0.0),
    ((0.0, 0.0, -1.0), None, 1.0),
    ((1.0, 1.0, 0.0), 0.375, 0.5),
    ((1.0, 0.0, 1.0), 0.5, 0.25),
]


@pytest.mark.parametrize("direction, u, v", KNOWN)
def test_direction_to_uv_at_known_directions(direction, u, v) -> None:
    got_u, got_v = direction_to_uv(tensor(*direction))
    if u is not None:
        assert float(got_u) == pytest.approx(u, abs=1e-12)
        scalar = torch.tensor
        torch.testing.assert_close(uv_to_direction(scalar(u, dtype=DTYPE), scalar(v, dtype=DTYPE)), unit(*direction),
                                   rtol=0.0, atol=1e-12)
    assert float(got_v) == pytest.approx(v, abs=1e-12)


def test_minus_x_is_on_the_seam() -> None:
    for d in (tensor(-1.0, 0.0, 0.0), tensor(-1.0, -0.0, 0.0), tensor(-1.0, 1e-12, 0.0), tensor(-1.0, -1e-12, 0.0)):
        u, _ = direction_to_uv(d)
        assert 0.0 <= float(u) < 1.0
        assert min(float(u), 1.0 - float(u)) < 1e-11


def test_rows_and_columns_of_known_directions() -> None:
    H, W = 16, 32
    for d, row, col in (((0.0, 0.0, 1.0), 0, None), ((0.0, 0.0, -1.0), H - 1, None), ((1.0, 0.0, 0.0), H // 2, W // 2),
                        ((0.0, 1.0, 0.01), H // 2 - 1, W // 4), ((0.0, -1.0, -0.01), H // 2, 3 * W // 4)):
        r, c = direction_to_pixel(tensor(*d), H, W)
        assert int(r) == row
        if col is not None:
            assert int(c) == col


def test_uv_direction_round_trips() -> None:
    gen = torch.Generator().manual_seed(11)
    d = torch.nn.functional.normalize(torch.randn(10_000, 3, generator=gen, dtype=DTYPE), dim=-1)
    u, v = direction_to_uv(d)
    assert bool(((u >= 0) & (u < 1) & (v >= 0) & (v <= 1)).all())
    torch.testing.assert_close(uv_to_direction(u, v), d, rtol=0.0, atol=1e-12)
    # non-unit input is normalised first
    torch.testing.assert_close(torch.stack(direction_to_uv(3.5 * d)), torch.stack((u, v)), rtol=0.0, atol=1e-12)
    u2 = torch.rand(10_000, generator=gen, dtype=DTYPE)
    v2 = 1e-6 + (1 - 2e-6) * torch.rand(10_000, generator=gen, dtype=DTYPE)
    back_u, back_v = direction_to_uv(uv_to_direction(u2, v2))
    du = torch.remainder(back_u - u2 + 0.5, 1.0) - 0.5
    assert float(du.abs().max()) < 1e-9
    torch.testing.assert_close(back_v, v2, rtol=0.0, atol=1e-12)


def test_pixel_directions_are_the_pixel_centres() -> None:
    H, W = 9, 20
    d = pixel_directions(H, W, dtype=DTYPE)
    assert d.shape == (H, W, 3)
    torch.testing.assert_close(d.norm(dim=-1), torch.ones(H, W, dtype=DTYPE))
    rows, cols = direction_to_pixel(d, H, W)
    assert torch.equal(rows, torch.arange(H).unsqueeze(-1).expand(H, W))
    assert torch.equal(cols, torch.arange(W).expand(H, W))


@pytest.mark.parametrize("H, W", ((1, 2), (8, 16), (33, 64), (256, 512)))
def test_pixel_solid_angles_sum_to_4pi(H: int, W: int) -> None:
    omega = pixel_solid_angles(H, W, dtype=DTYPE)
    assert omega.shape == (H, 1) and bool((omega > 0).all())
    assert float(omega.sum() * W) == pytest.approx(4.0 * math.pi, rel=1e-12)
    # each row's pixels are the zone between its edges: 2 pi (cos top - cos bottom) / W
    top, bottom = torch.arange(H, dtype=DTYPE) * math.pi / H, torch.arange(1, H + 1, dtype=DTYPE) * math.pi / H
    torch.testing.assert_close(omega[:, 0], 2 * math.pi * (torch.cos(top) - torch.cos(bottom)) / W)


def convention_direction(u: float, v: float) -> torch.Tensor:
    """The documented mapping, written out here: ``phi = pi (1 - 2u)``, ``theta = pi v``."""
    phi, theta = math.pi * (1.0 - 2.0 * u), math.pi * v
    return tensor(math.sin(theta) * math.cos(phi), math.sin(theta) * math.sin(phi), math.cos(theta))


H_IMG, W_IMG = 33, 65   # odd, so +X (u = v = 0.5) is a pixel centre


def lobe_axes():
    """``(name, axis, at_pixel_centre)``."""
    yield "+X", tensor(1.0, 0.0, 0.0), True
    yield "+Y", convention_direction(0.25, 0.5), False       # u = 0.25 is a quarter into column 16 of 65
    yield "-Y", convention_direction(0.75, 0.5), False
    for name, (row, col) in {"r3c10": (3, 10), "r20c50": (20, 50), "r31c1": (31, 1), "r12c64": (12, 64)}.items():
        yield name, convention_direction((col + 0.5) / W_IMG, (row + 0.5) / H_IMG), True
    # well inside a pixel but off its centre, away from the poles
    yield "off-centre", convention_direction((40 + 0.25) / W_IMG, (10 + 0.7) / H_IMG), False


@pytest.mark.parametrize("name, axis, at_pixel_centre", list(lobe_axes()))
def test_sg_to_equirect_puts_a_sharp_lobe_at_its_pixel(name: str, axis: torch.Tensor, at_pixel_centre: bool) -> None:
    sg = one_lobe(axis, 20_000.0, (3.0, 2.0, 1.0))
    img = sg_to_equirect(sg, H_IMG, W_IMG)
    assert img.shape == (H_IMG, W_IMG, 3)
    peak = int(img[..., 0].argmax())
    row, col = direction_to_pixel(axis, H_IMG, W_IMG)
    assert (peak // W_IMG, peak % W_IMG) == (int(row), int(col))
    if at_pixel_centre:      # the lobe's full amplitude is in that pixel
        torch.testing.assert_close(img[int(row), int(col)], tensor(3.0, 2.0, 1.0), rtol=1e-9, atol=0.0)


def test_sg_to_equirect_of_plus_z_lights_the_top_row() -> None:
    img = sg_to_equirect(one_lobe(tensor(0.0, 0.0, 1.0), 50.0), 16, 32)
    assert int(img[..., 0].argmax()) // 32 == 0
    torch.testing.assert_close(img[0, :, 0], img[0, :1, 0].expand(32))      # symmetric about the pole


# --------------------------------------------------------------------------- fibonacci sphere


@pytest.mark.parametrize("n", (1, 2, 7, 128, 1000))
def test_fibonacci_sphere_is_unit_and_spread(n: int) -> None:
    p = fibonacci_sphere(n, dtype=DTYPE)
    assert p.shape == (n, 3)
    torch.testing.assert_close(p.norm(dim=-1), torch.ones(n, dtype=DTYPE), rtol=0.0, atol=1e-12)
    if n >= 7:
        # nearly uniform: no two points closer than half the mean spacing sqrt(4 pi / n)
        dist = torch.cdist(p, p) + 10.0 * torch.eye(n, dtype=DTYPE)
        assert float(dist.min()) > 0.5 * math.sqrt(4.0 * math.pi / n)
    if n >= 128:
        assert float(p.mean(0).norm()) < 2.0 / n
        assert float((p[:, 2] > 0).double().mean()) == pytest.approx(0.5, abs=1.0 / n)


def test_detaching_the_sharp_lobes_keeps_the_value_and_stops_their_gradient() -> None:
    g = torch.Generator().manual_seed(0)
    axis = torch.nn.functional.normalize(torch.randn(6, 3, generator=g), dim=-1).requires_grad_(True)
    sharpness = torch.tensor([5.0, 500.0, 20.0, 2000.0, 1.0, 300.0], requires_grad=True)
    amplitude = torch.rand(6, 3, generator=g).requires_grad_(True)
    w = torch.nn.functional.normalize(torch.randn(64, 3, generator=g), dim=-1)
    sg = SGMixture(axis, sharpness, amplitude)
    held = sg_detach_sharper(sg, 250.0)
    assert torch.equal(sg_eval(w, held), sg_eval(w, sg))
    sg_eval(w, held).sum().backward()
    sharp = sharpness.detach() > 250.0
    for p in (axis, amplitude):
        assert bool((p.grad[sharp] == 0).all()) and bool((p.grad[~sharp].abs().sum(-1) > 0).all())
    assert bool((sharpness.grad[sharp] == 0).all()) and bool((sharpness.grad[~sharp] != 0).all())


def test_the_cache_holds_lobes_up_to_its_direction_encodings_bandwidth() -> None:
    """F Fourier frequencies reach pi 2^(F-1); a lobe of sharpness lambda has its spectrum at e^-1 at sqrt(2
    lambda): the limit is (pi 2^(F-1))^2 / 2, four times higher for each frequency added."""
    from nefii.fields.cache import RadianceCache
    from nefii.fields.encodings import HashGrid
    box = (torch.zeros(3), torch.ones(3))
    four = RadianceCache(HashGrid(2, 2, 8, 4, 8), 4, 8, 1, box).max_lobe_sharpness
    assert four == pytest.approx((8 * math.pi) ** 2 / 2)
    assert RadianceCache(HashGrid(2, 2, 8, 4, 8), 5, 8, 1, box).max_lobe_sharpness == pytest.approx(4 * four)
