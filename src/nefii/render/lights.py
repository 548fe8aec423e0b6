"""Light-sampling strategies for the estimator: one protocol and the SG mixture behind it (an env map is
:class:`nefii.render.envmap.Environment`, which is a light sampler too).

A strategy draws directions at shading points with normal ``n`` and reports the density of
any direction over solid angle; ``n`` may shape the distribution (the SG lobe choice of Eq. 6).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

from jaxtyping import Float
from torch import Tensor

from .samplers import SG_HEMISPHERE_EPS, pdf_sg_mixture, sample_sg_mixture, sg_selection_probs
from .sg import SGMixture, sg_lobes


class LightSampler(Protocol):
    def sample(self, n: Float[Tensor, "*bs 3"], u: Float[Tensor, "*bs N 3"]) -> Float[Tensor, "*bs N 3"]: ...

    def pdf(self, n: Float[Tensor, "*bs 3"], wi: Float[Tensor, "*bs S 3"]) -> Float[Tensor, "*bs S"]: ...


@dataclass(frozen=True)
class SGLightSampler:
    """Eq. 5-6: a lobe by energy times ``max(n . xi, eps)``, then the lobe exactly."""

    sg: SGMixture
    eps: float = SG_HEMISPHERE_EPS

    def sample(self, n: Tensor, u: Tensor) -> Tensor:
        return sample_sg_mixture(self.sg, sg_selection_probs(self.sg, n, self.eps).unsqueeze(-2), u)

    def pdf(self, n: Tensor, wi: Tensor) -> Tensor:
        return self.pdf_and_lobes(n, wi)[0]

    def pdf_and_lobes(self, n: Float[Tensor, "*bs 3"], wi: Float[Tensor, "*bs S 3"]
                      ) -> tuple[Float[Tensor, "*bs S"], Float[Tensor, "*bs S K"]]:
        """:meth:`pdf` and the unit lobe values ``sg_lobes(wi, sg)`` it is made of (the radiance of the
        directions that escape is those values times the amplitudes: the caller need not compute them again)."""
        lobes = sg_lobes(wi, self.sg)
        return pdf_sg_mixture(self.sg, sg_selection_probs(self.sg, n, self.eps).unsqueeze(-2), wi, lobes), lobes


def as_light_sampler(light: SGMixture | LightSampler) -> LightSampler:
    return SGLightSampler(light) if isinstance(light, SGMixture) else light
