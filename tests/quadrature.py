"""Graded Gauss-Legendre quadrature over the sphere, shared by the statistical tests.

A direction is written in a frame centred on a unit vector ``c`` as ``t = 1 - cos(theta')``
in ``[0, 2]`` and an azimuth ``phi'`` in ``[0, 2 pi)``, so that ``d omega = dt dphi'``.
The distributions under test are sharp about ``c`` (GGX with alpha ~ 0.008 lives at
``t ~ 1e-4``, an SG of sharpness 1000 at ``t ~ 1e-3``) and have long tails, so ``t`` is
integrated with a composite Gauss-Legendre rule in ``s = log(t + eps)`` (a geometric
grading towards ``c``) whose panels are also at most ``dt_max`` wide in ``t`` (so that
features far from ``c``, such as other lobes of a mixture, are resolved too); ``phi'`` with a
composite rule of uniform panels. Everything is float64 and independent of
``nefii.render.frame`` (whose ``Frame`` is under test elsewhere).
"""
from __future__ import annotations

import math
from typing import Callable

import numpy as np
import torch
from torch import Tensor

DTYPE = torch.float64
Integrand = Callable[[Tensor], Tensor]
"""``(..., 3)`` unit directions -> ``(...)`` values, or ``(..., C)`` for C integrals at once."""


def orthonormal_frame(c) -> tuple[Tensor, Tensor, Tensor]:
    """``(c, e1, e2)``, right-handed, by Gram-Schmidt against the least aligned coordinate axis."""
    c = torch.as_tensor(c, dtype=DTYPE)
    c = c / c.norm()
    helper = torch.zeros(3, dtype=DTYPE)
    helper[int(torch.argmin(c.abs()))] = 1.0
    e1 = helper - (helper @ c) * c
    e1 = e1 / e1.norm()
    e2 = torch.linalg.cross(c, e1)
    return c, e1, e2


def centred_direction(frame: tuple[Tensor, Tensor, Tensor], t: Tensor, phi: Tensor) -> Tensor:
    """Unit direction at ``(t, phi)`` about ``frame[0]``; ``t`` and ``phi`` broadcast."""
    c, e1, e2 = frame
    t, phi = torch.broadcast_tensors(t, phi)
    cos_t = (1.0 - t).unsqueeze(-1)
    sin_t = (t * (2.0 - t)).clamp_min(0.0).sqrt().unsqueeze(-1)
    return cos_t * c + sin_t * (torch.cos(phi).unsqueeze(-1) * e1 + torch.sin(phi).unsqueeze(-1) * e2)


def centred_coordinates(frame: tuple[Tensor, Tensor, Tensor], w: Tensor) -> tuple[Tensor, Tensor]:
    """``(t, phi)`` of directions ``w`` about ``frame[0]``; ``t = |w - c|^2 / 2`` keeps its precision near ``c``."""
    c, e1, e2 = frame
    w = w / w.norm(dim=-1, keepdim=True)
    t = 0.5 * ((w - c) ** 2).sum(-1)
    phi = torch.remainder(torch.atan2(w @ e2, w @ e1), 2.0 * math.pi)
    return t, phi


def _reference_rule(order: int) -> tuple[Tensor, Tensor]:
    x, w = np.polynomial.legendre.leggauss(order)
    return torch.as_tensor(0.5 * (x + 1.0), dtype=DTYPE), torch.as_tensor(0.5 * w, dtype=DTYPE)


def uniform_rule(lo: float, hi: float, panels: int, order: int) -> tuple[Tensor, Tensor]:
    """Composite Gauss-Legendre nodes and weights on ``[lo, hi]`` with ``panels`` equal panels."""
    x, w = _reference_rule(order)
    edges = torch.linspace(lo, hi, panels + 1, dtype=DTYPE)
    width = (edges[1:] - edges[:-1]).unsqueeze(-1)
    return (edges[:-1].unsqueeze(-1) + width * x).reshape(-1), (width * w).reshape(-1)


def graded_rule(t_lo: float, t_hi: float, eps: float, order: int = 5, ds_max: float = 0.5,
                dt_max: float = 0.05) -> tuple[Tensor, Tensor]:
    """Nodes and weights in ``t`` on ``[t_lo, t_hi]``: panels uniform in ``log(t + eps)``, at most ``dt_max`` wide."""
    s_lo, s_hi = math.log(t_lo + eps), math.log(t_hi + eps)
    # panel edges: geometric in t + eps, then refined where a panel is wider than dt_max
    edges = [t_lo]
    for s in np.linspace(s_lo, s_hi, max(1, math.ceil((s_hi - s_lo) / ds_max)) + 1)[1:]:
        nxt = min(t_hi, math.exp(s) - eps)
        prev = edges[-1]
        pieces = max(1, math.ceil((nxt - prev) / dt_max))
        edges.extend(prev + (nxt - prev) * (i + 1) / pieces for i in range(pieces))
    edges_t = torch.tensor(edges, dtype=DTYPE)
    s_edges = torch.log(edges_t + eps)
    x, w = _reference_rule(order)
    ds = (s_edges[1:] - s_edges[:-1]).unsqueeze(-1)
    s = s_edges[:-1].unsqueeze(-1) + ds * x
    t = torch.exp(s) - eps
    return t.reshape(-1), (ds * w * torch.exp(s)).reshape(-1)


def _weighted_sum(weights: Tensor, values: Tensor) -> float | Tensor:
    """Sum of ``weights * values`` over the node axes; a float, or a (C,) tensor for vector integrands."""
    extra = values.dim() - weights.dim()
    total = (weights.reshape(*weights.shape, *(1,) * extra) * values).sum(tuple(range(weights.dim())))
    return float(total) if extra == 0 else total


def integrate_sphere(f: Integrand, centre, *, eps: float = 1e-6, order: int = 6, ds_max: float = 0.25,
                     dt_max: float = 0.02, phi_panels: int = 128, t_max: float = 2.0) -> float | Tensor:
    """``int f(w) dw`` over the cap ``1 - w.c <= t_max`` (the whole sphere by default)."""
    frame = orthonormal_frame(centre)
    t, wt = graded_rule(0.0, t_max, eps, order, ds_max, dt_max)
    phi, wp = uniform_rule(0.0, 2.0 * math.pi, phi_panels, order)
    values = f(centred_direction(frame, t.unsqueeze(-1), phi))
    return _weighted_sum(wt.unsqueeze(-1) * wp, values)


def integrate_upper_hemisphere(f: Integrand, centre, *, eps: float = 1e-6, order: int = 6, ds_max: float = 0.25,
                               dt_max: float = 0.02, phi_panels: int = 128) -> float | Tensor:
    """``int f(w) dw`` over ``w.z > 0``, in a frame centred on ``centre`` (which must be above the horizon).

    Along the azimuth ``phi'`` the height is ``w.z = R cos(theta' - delta)`` with
    ``R = sqrt(c_z^2 + A^2)``, ``delta = atan2(A, c_z)``, ``A = cos(phi') e1_z + sin(phi') e2_z``, so the
    hemisphere ends at ``t_max(phi') = 1 + A / R``. The rule in ``t`` is the graded rule on
    ``[0, 1]`` scaled by ``t_max(phi')``: the horizon lies on the grid, and a discontinuity of
    ``f`` there (an indicator, a clamp) costs no accuracy.
    """
    frame = orthonormal_frame(centre)
    c, e1, e2 = frame
    if float(c[2]) <= 0.0:
        raise ValueError("integrate_upper_hemisphere wants a centre above the horizon")
    phi, wp = uniform_rule(0.0, 2.0 * math.pi, phi_panels, order)
    a = torch.cos(phi) * e1[2] + torch.sin(phi) * e2[2]
    t_hi = (1.0 + a / (c[2] ** 2 + a * a).sqrt()).unsqueeze(-1)                   # (P, 1)
    tau, w_tau = graded_rule(0.0, 1.0, eps, order, ds_max, dt_max)
    values = f(centred_direction(frame, t_hi * tau, phi.unsqueeze(-1)))             # (P, M)
    return _weighted_sum(t_hi * w_tau * wp.unsqueeze(-1), values)
