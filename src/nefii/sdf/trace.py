"""Sphere tracing of a frozen SDF behind the :class:`~nefii.raycast.base.Geometry` contract (the paper's
way of finding first hits and secondary hits), with the SDF's feature vector f at each hit."""
from __future__ import annotations

import torch
from jaxtyping import Bool
from torch import Tensor

from ..raycast.base import Rays, SurfaceHit
from .networks import SDFNetwork
from .normalization import Normalization
from .volume import sphere_bounds


class SDFGeometry:
    """``intersect`` by sphere tracing inside the unit sphere: steps of ``step_scale * f`` (at least
    ``min_step``) until ``|f| < eps``; a step that lands inside (``f < 0``) is refined by bisection
    against the last point outside, so a learned SDF that is not an exact distance cannot tunnel."""

    def __init__(self, sdf: SDFNetwork, norm: Normalization, max_steps: int = 192, eps: float = 1e-4,
                 step_scale: float = 0.9, min_step: float = 1e-4, bisections: int = 10, chunk: int = 262144) -> None:
        self.sdf, self.norm = sdf.eval(), norm
        self.max_steps, self.eps, self.step_scale, self.min_step = max_steps, eps, step_scale, min_step
        self.bisections, self.chunk = bisections, chunk
        c, r = torch.tensor(norm.center), norm.radius
        self.bounds = ((c - r).numpy(), (c + r).numpy())
        self.scale = float(2 * r * 3**0.5)
        """diagonal of the sphere's bounding cube"""
        for p in self.sdf.parameters():
            p.requires_grad_(False)

    @torch.no_grad()
    def _trace(self, o: Tensor, d: Tensor, t_max: Tensor) -> tuple[Tensor, Tensor]:
        """Unit-space hit distances and validity."""
        near, far, inside = sphere_bounds(o, d)
        far = torch.minimum(far, t_max)
        t = near.clone()
        t_out = near.clone()                                         # last distance known outside
        active = inside & (near < far)
        hit = torch.zeros_like(active)
        for _ in range(self.max_steps):
            idx = active.nonzero(as_tuple=True)[0]
            if len(idx) == 0:
                break
            f = self.sdf.sdf(o[idx] + t[idx, None] * d[idx])
            done = f.abs() < self.eps
            crossed = f < 0
            hit[idx[done]] = True
            # bisection where the step went inside
            bi = idx[crossed & ~done]
            if len(bi):
                lo, hi = t_out[bi], t[bi]
                for _ in range(self.bisections):
                    mid = 0.5 * (lo + hi)
                    fm = self.sdf.sdf(o[bi] + mid[:, None] * d[bi])
                    lo, hi = torch.where(fm > 0, mid, lo), torch.where(fm > 0, hi, mid)
                t[bi] = 0.5 * (lo + hi)
                hit[bi] = True
            go = ~done & ~crossed
            gi = idx[go]
            t_out[gi] = t[gi]
            t[gi] = t[gi] + torch.clamp(self.step_scale * f[go], min=self.min_step)
            active[idx[done | crossed]] = False
            active[gi[t[gi] > far[gi]]] = False
        return t, hit & (t <= far)

    def intersect(self, rays: Rays) -> SurfaceHit:
        o_w, d = rays.origins.reshape(-1, 3), rays.directions.reshape(-1, 3)
        dev, dtype = o_w.device, o_w.dtype
        p = next(self.sdf.parameters())
        o = self.norm.to_unit(o_w.to(p.device, torch.float32))
        dd = d.to(p.device, torch.float32)
        t_max = torch.full((len(o),), float("inf"), device=p.device) if rays.t_max is None else \
            rays.t_max.reshape(-1).to(p.device, torch.float32) / self.norm.radius
        ts, hits = [], []
        for s in range(0, len(o), self.chunk):
            t, h = self._trace(o[s:s + self.chunk], dd[s:s + self.chunk], t_max[s:s + self.chunk])
            ts.append(t)
            hits.append(h)
        t, valid = torch.cat(ts), torch.cat(hits)
        x = o + t[:, None] * dd
        _, grad, feat = self.sdf.with_gradient(x, create_graph=False)
        n = grad / grad.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        t_world = torch.where(valid, t * self.norm.radius, torch.full_like(t, float("inf")))
        pos = self.norm.to_world(x)
        shape = rays.origins.shape[:-1]
        n = n.to(dev, dtype).reshape(*shape, 3)                   # the SDF's gradient: every normal a hit has
        return SurfaceHit(valid=valid.to(dev).reshape(shape), t=t_world.to(dev, dtype).reshape(shape),
                          position=pos.to(dev, dtype).reshape(*shape, 3), normal=n, geometric_normal=n,
                          lookup_normal=n,
                          triangle_id=torch.full(shape, -1, dtype=torch.long, device=dev),
                          features=feat.to(dev, dtype).reshape(*shape, -1))

    def occluded(self, rays: Rays) -> Bool[Tensor, " *bs"]:
        return self.intersect(rays).valid
