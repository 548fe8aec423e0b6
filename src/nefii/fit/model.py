"""The thin model: the learned fields (paper Sec. 3.2, Fig. 2), their parameter groups, and the one
decode of the material at surface points.

``decode_material`` is the only way the recovered material is read: the fit, eval, relight,
export's bake and the benchmarks all call it, so they read the same albedo and roughness at a
surface point (the field's lookup ``x + offset * n`` takes the hit's ``lookup_normal``).
"""
from __future__ import annotations

from typing import Any

import torch
from jaxtyping import Float
from torch import Tensor, nn

from ..fields.cache import RadianceCache
from ..fields.environment import EnvmapEnvironment, SGEnvironment
from ..fields.material import MaterialField
from ..render.brdf import Material


class NeFIIModel(nn.Module):
    """Material field M, radiance cache L and environment E: everything that is learned."""

    def __init__(self, material: MaterialField, cache: RadianceCache, env: SGEnvironment | EnvmapEnvironment) -> None:
        super().__init__()
        self.material, self.cache, self.env = material, cache, env

    def param_groups(self, lr: float, lr_light: float, lr_light_shape: float) -> list[dict[str, Any]]:
        """Optimiser groups: the networks at ``lr``, the light's radiance at ``lr_light``, the SG lobes'
        axes and sharpness (if any) at ``lr_light_shape``. Frozen parameters (a frozen SDF's) are left out."""
        shape = [p for p in self.env.shape_parameters() if p.requires_grad]
        shape_ids = {id(p) for p in shape}
        light = [p for p in self.env.parameters() if p.requires_grad and id(p) not in shape_ids]
        env_ids = {id(p) for p in self.env.parameters()}
        nets = [p for p in self.parameters() if p.requires_grad and id(p) not in env_ids]
        groups = [{"params": nets, "lr": lr}, {"params": light, "lr": lr_light}]
        if shape:
            groups.append({"params": shape, "lr": lr_light_shape})
        return [g for g in groups if g["params"]]


def decode_material(model: NeFIIModel, position: Float[Tensor, "B 3"], lookup_normal: Float[Tensor, "B 3"],
                    roughness_override: float | None = None) -> Material:
    """The material at surface points ``position`` whose lookup normal (:attr:`SurfaceHit.lookup_normal`) is
    ``lookup_normal``: albedo ``(B, 3)`` linear in [0, 1], roughness ``(B,)``; ``roughness_override`` (the
    warm-up's constant) replaces the learned roughness. Differentiable; see :func:`material_at` for a
    chunked decode without gradient."""
    return model.material(position, lookup_normal, roughness_override=roughness_override)


@torch.no_grad()
def material_at(model: NeFIIModel, position: Float[Tensor, "N 3"], lookup_normal: Float[Tensor, "N 3"],
                chunk: int = 65536, progress=None) -> Material:
    """:func:`decode_material` over many points in chunks, without gradient, on the model's device.
    ``progress(n)`` is called with the number of points done after each chunk."""
    device = next(model.parameters()).device
    parts = []
    for part, nrm in zip(position.split(chunk), lookup_normal.split(chunk)):
        parts.append(decode_material(model, part.to(device=device, dtype=torch.float32),
                                     nrm.to(device=device, dtype=torch.float32)))
        if progress is not None:
            progress(len(part))
    if not parts:
        return decode_material(model, position.new_zeros(0, 3, device=device, dtype=torch.float32),
                               lookup_normal.new_zeros(0, 3, device=device, dtype=torch.float32))
    return Material(torch.cat([m.albedo for m in parts]), torch.cat([m.roughness for m in parts]), parts[0].brdf)
