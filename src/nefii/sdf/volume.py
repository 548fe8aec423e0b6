"""NeuS volume rendering of a signed distance field (Wang et al. 2021), as pure functions.

Along a ray, the opacity of a section between two samples follows from the SDF's logistic CDF
``Phi_s(f) = sigmoid(s f)``: ``alpha = max((Phi_s(f_prev) - Phi_s(f_next)) / Phi_s(f_prev), 0)``,
unbiased at the zero crossing. Shapes: ``R`` rays, ``S`` samples per ray.
"""
from __future__ import annotations

import torch
from jaxtyping import Bool, Float
from torch import Tensor


def sphere_bounds(o: Float[Tensor, "R 3"], d: Float[Tensor, "R 3"], radius: float = 1.0
                  ) -> tuple[Float[Tensor, " R"], Float[Tensor, " R"], Bool[Tensor, " R"]]:
    """Entry and exit distances of unit-direction rays through the sphere ``|x| = radius``
    (entry clamped at 0 for origins inside); ``hit`` is False where the ray misses it."""
    b = (o * d).sum(-1)
    c = (o * o).sum(-1) - radius * radius
    disc = b * b - c
    hit = disc > 0
    root = disc.clamp_min(0).sqrt()
    near, far = (-b - root).clamp_min(0.0), -b + root
    return near, far, hit & (far > 0)


def stratified_depths(near: Float[Tensor, " R"], far: Float[Tensor, " R"], n: int,
                      generator: torch.Generator | None = None, perturb: bool = True) -> Float[Tensor, "R n"]:
    """``n`` depths per ray, one per equal bin of ``[near, far]`` (jittered when ``perturb``)."""
    u = torch.arange(n, device=near.device, dtype=near.dtype)
    u = u + (torch.rand(len(near), n, generator=generator, device=near.device, dtype=near.dtype) if perturb else 0.5)
    t = u / n
    return near.unsqueeze(-1) + (far - near).unsqueeze(-1) * t


def section_alpha(sdf_prev: Tensor, sdf_next: Tensor, inv_s: Tensor | float) -> Tensor:
    """Opacity of a section whose ends have SDF ``sdf_prev`` then ``sdf_next`` (NeuS Eq. 13)."""
    prev_cdf = torch.sigmoid(sdf_prev * inv_s)
    next_cdf = torch.sigmoid(sdf_next * inv_s)
    return ((prev_cdf - next_cdf + 1e-5) / (prev_cdf + 1e-5)).clamp(0.0, 1.0)


def neus_alpha(sdf: Float[Tensor, "R S"], cos: Float[Tensor, "R S"], deltas: Float[Tensor, "R S"],
               inv_s: Tensor | float, cos_anneal: float = 1.0) -> Float[Tensor, "R S"]:
    """Section opacities from the SDF and its directional derivative ``cos = grad f . d`` at section
    midpoints: the ends are estimated as ``f -+ cos delta / 2``. ``cos_anneal`` < 1 (early training)
    lets back-facing sections contribute, as NeuS does, so the SDF can move freely at the start."""
    iter_cos = -(torch.relu(-cos * 0.5 + 0.5) * (1.0 - cos_anneal) + torch.relu(-cos) * cos_anneal)
    half = iter_cos * deltas * 0.5
    return section_alpha(sdf - half, sdf + half, inv_s)


def composite_weights(alpha: Float[Tensor, "R S"]) -> Float[Tensor, "R S"]:
    """``w_i = alpha_i prod_{j<i} (1 - alpha_j)``."""
    trans = torch.cumprod(torch.cat([alpha.new_ones(alpha.shape[0], 1), 1.0 - alpha + 1e-7], -1), -1)[:, :-1]
    return alpha * trans


def sample_pdf(edges: Float[Tensor, "R B1"], weights: Float[Tensor, "R B"], n: int) -> Float[Tensor, "R n"]:
    """``n`` deterministic (evenly spaced in the CDF) depths from the piecewise-constant density with
    ``weights`` over the bins between consecutive ``edges``."""
    w = weights + 1e-5
    pdf = w / w.sum(-1, keepdim=True)
    cdf = torch.cat([pdf.new_zeros(pdf.shape[0], 1), torch.cumsum(pdf, -1)], -1)       # (R, B+1)
    u = (torch.arange(n, device=edges.device, dtype=edges.dtype) + 0.5) / n
    u = u.expand(edges.shape[0], n).contiguous()
    idx = torch.searchsorted(cdf, u, right=True).clamp(1, cdf.shape[-1] - 1)
    c0, c1 = cdf.gather(-1, idx - 1), cdf.gather(-1, idx)
    e0, e1 = edges.gather(-1, idx - 1), edges.gather(-1, idx)
    t = ((u - c0) / (c1 - c0).clamp_min(1e-12)).clamp(0.0, 1.0)
    return e0 + t * (e1 - e0)


def upsample_depths(z: Float[Tensor, "R S"], sdf: Float[Tensor, "R S"], n: int, inv_s: float) -> Float[Tensor, "R n"]:
    """NeuS's hierarchical sampling: ``n`` new depths where the SDF at the current depths, rendered with a
    fixed sharpness ``inv_s``, puts its weight (the slope of each section is the smaller of its own and
    its predecessor's, clipped to facing the ray, which keeps weight off back faces)."""
    dz = z[:, 1:] - z[:, :-1]
    mid = 0.5 * (sdf[:, 1:] + sdf[:, :-1])
    cos = (sdf[:, 1:] - sdf[:, :-1]) / (dz + 1e-5)
    prev_cos = torch.cat([cos.new_zeros(cos.shape[0], 1), cos[:, :-1]], -1)
    cos = torch.minimum(cos, prev_cos).clamp(-1e3, 0.0)
    alpha = section_alpha(mid - cos * dz * 0.5, mid + cos * dz * 0.5, inv_s)
    return sample_pdf(z, composite_weights(alpha), n)
