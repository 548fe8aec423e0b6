"""The SG environment's amplitudes solved exactly, given everything else the fit holds.

Adam moves every amplitude by about its learning rate a step, whatever its gradient says, so the light drifts
where the images constrain it weakly and the albedo pays for it (docs/experiments.md, 2026-11-26 and
2026-11-27). But with the lobes' axes and sharpness, the material, the cache and the estimator's samples
fixed, Eq. 7 is a quadratic in the amplitudes: the estimate of Eq. 2-4 is linear in the incoming radiance
(``1/N sum_s T_s L_i(w_s)``, ``T_s`` the sample's BRDF, cosine, MIS weight over its pdf), the radiance of an
escaping ray is ``sum_k mu_k G_k(w_s)`` (``G_k`` the lobe's unit Gaussian), and a hit's is the cache's. So
every ``light_solve_every`` steps the amplitudes are set to the minimiser over ``mu >= 0``, per channel, of

    mean_b w_b^2 (B1_b mu + c1_b - t_b)(B2_b mu + c2_b - t_b)        (Eq. 7's pair loss, ``l2_pair``)
    + beta2 mean_q w_q^2 (G_q mu - t_q)^2                              (background pixels, tone map linearised)
    + the unseen-light prior's gradient at the current energy           (:mod:`nefii.fit.light_prior`)

with ``B1``, ``B2`` the two half estimates' lobe designs (their cross product keeps the estimate's variance out
of the solution, as the pair loss does), ``w`` the tone map's slope at the target. Eq. 8 and the other
parameters then go on learning by Adam between solves.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
from jaxtyping import Float
from torch import Tensor

from ..raycast.base import Geometry
from ..render.brdf import Material
from ..render.estimator import DirectionSamples, combine_pair
from ..render.sg import SGMixture, sg_lobes
from .distributed import DistContext, all_mean
from .path_trace import SurfacePoints, Transport, trace_live_samples


@dataclass(frozen=True)
class Quadratic:
    """``x^T A x - 2 r^T x`` per channel, minimised over ``x >= 0``."""

    A: Float[Tensor, "C K K"]
    r: Float[Tensor, "C K"]

    def __add__(self, other: "Quadratic") -> "Quadratic":
        return Quadratic(self.A + other.A, self.r + other.r)

    def scaled(self, s: float) -> "Quadratic":
        return Quadratic(self.A * s, self.r * s)


@dataclass(frozen=True)
class LobeDesign:
    """Two independent half estimates of points' outgoing radiance, each ``B mu + c`` in the amplitudes."""

    B: tuple[Float[Tensor, "P 3 K"], Float[Tensor, "P 3 K"]]
    c: tuple[Float[Tensor, "P 3"], Float[Tensor, "P 3"]]
    """what the secondary rays that hit the object (the cache) add"""


def sample_throughput(samples: DirectionSamples, material: Material, normal: Tensor
                      ) -> tuple[Float[Tensor, "P S 3"], Float[Tensor, "P S 3"]]:
    """``d estimate_h / d L_i``: each sample's weight in either half estimate (the estimator is linear in
    ``L_i``, so this is exact)."""
    L = torch.zeros_like(samples.wi, requires_grad=True)
    with torch.enable_grad():
        h1, h2 = combine_pair(samples, material, normal, L)
        t1 = torch.autograd.grad(h1.rgb.sum(), L, retain_graph=True)[0]
        t2 = torch.autograd.grad(h2.rgb.sum(), L)[0]
    return t1, t2


@torch.no_grad()
def lobe_design(pts: SurfacePoints, material: Material, samples: DirectionSamples, sg: SGMixture,
                geometry: Geometry, cache, transport: Transport) -> LobeDesign:
    """The design of :class:`LobeDesign` at ``pts`` for the drawn ``samples`` (secondary rays traced
    against ``geometry``; ``cache(x', n', wo')`` the radiance where they hit). Samples drawn with an SG light
    carry its lobe values (:attr:`DirectionSamples.light_lobes`), which are taken as ``sg``'s: draw them
    from ``sg`` itself."""
    wi = samples.wi
    live = trace_live_samples(pts, samples, geometry, transport)
    b_idx, s_idx, w_live = live.point, live.sample, live.direction
    L_hit = wi.new_zeros(wi.shape)
    escapes = live.escapes
    if live.hit is not None and transport.indirect and bool(live.hit.valid.any()):
        hit = live.hit
        L_hit[b_idx[hit.valid], s_idx[hit.valid]] = cache(hit.position[hit.valid], hit.normal[hit.valid],
                                                          -w_live[hit.valid])
    t1, t2 = sample_throughput(samples, material, pts.normal)
    # every direction's lobe values (drawn from ``sg``: its pdf's), the throughput of those that hit zeroed
    G = sg_lobes(wi, sg) if samples.light_lobes is None else samples.light_lobes
    escaped = torch.zeros(wi.shape[:2], dtype=torch.bool, device=wi.device)
    escaped[b_idx[escapes], s_idx[escapes]] = True
    e = escaped.unsqueeze(-1).to(t1.dtype)
    return LobeDesign((torch.einsum("psc,psk->pck", t1 * e, G), torch.einsum("psc,psk->pck", t2 * e, G)),
                      ((t1 * L_hit).sum(1), (t2 * L_hit).sum(1)))


def pixel_quadratic(design: LobeDesign, target: Float[Tensor, "P 3"], weight: Float[Tensor, "P 3"],
                    gain: Float[Tensor, "P 3"] | None = None) -> Quadratic:
    """Eq. 7's pair loss ``mean w^2 (g(B1 mu + c1) - t)(g(B2 mu + c2) - t)`` as a :class:`Quadratic` (the
    constant dropped, the cross term symmetrised)."""
    g = torch.ones_like(target) if gain is None else gain
    B1, B2 = (b.double() * g.double().unsqueeze(-1) for b in design.B)
    r1, r2 = ((target - g * c).double() for c in design.c)
    w2 = weight.double() ** 2
    A = 0.5 * (torch.einsum("pc,pck,pcj->ckj", w2, B1, B2) + torch.einsum("pc,pck,pcj->ckj", w2, B2, B1))
    r = 0.5 * (torch.einsum("pc,pck,pc->ck", w2, B1, r2) + torch.einsum("pc,pck,pc->ck", w2, B2, r1))
    return Quadratic(A / len(target), r / len(target))


def background_quadratic(sg: SGMixture, dirs: Float[Tensor, "Q 3"], target: Float[Tensor, "Q 3"],
                         weight: Float[Tensor, "Q 3"], gain: Float[Tensor, "Q 3"] | None = None) -> Quadratic:
    """``mean w^2 (g G mu - t)^2`` of background pixels as a :class:`Quadratic`."""
    g = torch.ones_like(target) if gain is None else gain
    G = sg_lobes(dirs, sg).double().unsqueeze(1) * g.double().unsqueeze(-1)      # (Q, 3, K)
    w2 = weight.double() ** 2
    return Quadratic(torch.einsum("qc,qck,qcj->ckj", w2, G, G) / len(dirs),
                     torch.einsum("qc,qck,qc->ck", w2, G, target.double()) / len(dirs))


def linear_term(coefficient: Float[Tensor, " K"], channels: int = 3) -> Quadratic:
    """``sum_k p_k x_ck`` in every channel's objective as a :class:`Quadratic` (a zero ``A``, ``r = -p / 2``)."""
    K = len(coefficient)
    return Quadratic(torch.zeros(channels, K, K, dtype=torch.float64, device=coefficient.device),
                     -0.5 * coefficient.double().expand(channels, K).clone())


def average_quadratic(q: Quadratic, ctx: DistContext) -> Quadratic:
    """The mean of every process's :class:`Quadratic` (a collective; the processes then solve the same)."""
    A, r = all_mean([q.A, q.r], ctx)
    return Quadratic(A.view_as(q.A), r.view_as(q.r))


def solve_nonnegative(q: Quadratic, x0: Float[Tensor, "C K"], iterations: int = 800) -> Float[Tensor, "C K"]:
    """``argmin_{x >= 0} x^T A x - 2 r^T x`` per channel by accelerated projected gradient from ``x0``; ``A`` is
    symmetrised and given a ridge of 1e-6 of its mean diagonal (Monte Carlo cross products need not be
    positive definite)."""
    A = 0.5 * (q.A + q.A.transpose(1, 2))
    ridge = 1e-6 * A.diagonal(dim1=1, dim2=2).mean(-1).clamp_min(1e-30)
    A = A + torch.diag_embed(ridge.unsqueeze(-1).expand_as(q.r))
    v = torch.ones_like(q.r).unsqueeze(-1)
    for _ in range(50):                                           # largest eigenvalue, by power iteration
        v = A @ v
        lip = v.norm(dim=1, keepdim=True).clamp_min(1e-30)
        v = v / lip
    step = 0.5 / lip.squeeze(-1)                                  # 1 / (2 lambda_max), per channel
    x, y, t = x0.double().clamp_min(0.0), x0.double().clamp_min(0.0), 1.0
    for _ in range(iterations):
        grad = 2.0 * (A @ y.unsqueeze(-1)).squeeze(-1) - 2.0 * q.r
        x_new = (y - step * grad).clamp_min(0.0)
        t_new = 0.5 * (1.0 + (1.0 + 4.0 * t * t) ** 0.5)
        y = x_new + ((t - 1.0) / t_new) * (x_new - x)
        x, t = x_new, t_new
    return x
