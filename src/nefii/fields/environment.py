"""The learnable SG environment ``E(w)``: K lobes with learnable axis, sharpness and RGB amplitude."""
from __future__ import annotations

import math

import torch
from jaxtyping import Float
from torch import Tensor, nn

from ..render.envmap import Environment, envmap_lookup
from ..render.equirect import pixel_directions, pixel_solid_angles
from ..render.frame import normalize
from ..render.lights import LightSampler, SGLightSampler
from ..render.sg import SGMixture, fibonacci_sphere, sg_energy, sg_eval, sg_to_equirect


class SGEnvironment(nn.Module):
    """``K`` spherical Gaussians, parameterised so every setting of the parameters is valid.

    axis = normalize(raw axis); sharpness = exp(log sharpness); amplitude = exp(log amplitude).
    Initial axes are a spherical Fibonacci lattice; initial sharpness is spread log-uniformly
    over ``[sharpness_min, sharpness_max]`` across the lobes (so some lobes start sharp enough to
    become a sun, others wide enough to be a sky), initial amplitude ``init_radiance`` spread
    so that the mixture starts near a constant environment of that radiance.
    """

    def __init__(self, num_lobes: int = 128, sharpness_min: float = 5.0, sharpness_max: float = 2000.0,
                 init_radiance: float = 0.5, seed: int = 0) -> None:
        super().__init__()
        g = torch.Generator().manual_seed(seed)
        self.axis_raw = nn.Parameter(fibonacci_sphere(num_lobes))
        t = torch.randperm(num_lobes, generator=g).float() / max(num_lobes - 1, 1)
        log_sharp = math.log(sharpness_min) + t * (math.log(sharpness_max) - math.log(sharpness_min))
        self.log_sharpness = nn.Parameter(log_sharp)
        # a lobe of sharpness lambda delivers ~2 pi / lambda of a constant unit environment;
        # share 4 pi init_radiance between lobes
        sharp = log_sharp.exp()
        integral = 2 * math.pi / sharp * (1 - torch.exp(-2 * sharp))
        mu = init_radiance * 4 * math.pi / (num_lobes * integral)
        self.log_amplitude = nn.Parameter(mu.log().unsqueeze(-1).repeat(1, 3))

    def shape_parameters(self) -> list[nn.Parameter]:
        """The lobes' axes and log-sharpness (the optimiser moves them more slowly than the amplitudes)."""
        return [self.axis_raw, self.log_sharpness]

    @torch.no_grad()
    def scale_radiance(self, k: float) -> None:
        """Every lobe's amplitude times ``k`` (> 0), in place."""
        self.log_amplitude.add_(math.log(k))

    def forward(self) -> SGMixture:
        return SGMixture(axis=normalize(self.axis_raw), sharpness=self.log_sharpness.exp(),
                         amplitude=self.log_amplitude.exp())

    def radiance(self, w: Float[Tensor, "*bs 3"], lobes: Float[Tensor, "*bs K"] | None = None
                 ) -> Float[Tensor, "*bs 3"]:
        """``E(w)``; ``lobes``: the unit lobe values at ``w`` when the caller has them (:func:`sg_eval`)."""
        return sg_eval(w, self(), lobes)

    def energy_atoms(self) -> tuple[Float[Tensor, "K 3"], Float[Tensor, " K"]]:
        """Each lobe's axis and energy (Eq. 6's ``mu_bar``: what it sends over the whole sphere)."""
        sg = self()
        return sg.axis, sg_energy(sg)

    def light_sampler(self) -> LightSampler:
        """Eq. 5-6 sampling of the current lobes (no gradient flows through sampling)."""
        sg = self()
        return SGLightSampler(SGMixture(sg.axis.detach(), sg.sharpness.detach(), sg.amplitude.detach()))

    def to_equirect(self, height: int, width: int) -> Float[Tensor, "H W 3"]:
        return sg_to_equirect(self(), height, width)


class EnvmapEnvironment(nn.Module):
    """The ablation of Fig. 5: an equirectangular grid of free RGB radiance values (log-parameterised),
    looked up piecewise-constantly and sampled by its piecewise-constant 2D distribution."""

    def __init__(self, height: int = 32, width: int = 64, init_radiance: float = 0.5) -> None:
        super().__init__()
        self.log_radiance = nn.Parameter(torch.full((height, width, 3), math.log(init_radiance)))

    def shape_parameters(self) -> list[nn.Parameter]:
        """None: a grid has only radiance."""
        return []

    @torch.no_grad()
    def scale_radiance(self, k: float) -> None:
        """Every pixel's radiance times ``k`` (> 0), in place."""
        self.log_radiance.add_(math.log(k))

    def image(self) -> Float[Tensor, "H W 3"]:
        return self.log_radiance.exp()

    def radiance(self, w: Float[Tensor, "*bs 3"]) -> Float[Tensor, "*bs 3"]:
        return envmap_lookup(self.image(), w)

    def energy_atoms(self) -> tuple[Float[Tensor, "HW 3"], Float[Tensor, " HW"]]:
        """Each pixel's direction and energy (mean RGB radiance times its solid angle)."""
        img = self.image()
        h, w = img.shape[:2]
        d = pixel_directions(h, w, device=img.device, dtype=img.dtype)
        return d.reshape(-1, 3), (img.mean(-1) * pixel_solid_angles(h, w, device=img.device, dtype=img.dtype)).reshape(-1)

    def light_sampler(self) -> LightSampler:
        return Environment.from_image(self.image().detach())

    def to_equirect(self, height: int, width: int) -> Float[Tensor, "H W 3"]:
        d = pixel_directions(height, width, device=self.log_radiance.device)
        return self.radiance(d)
