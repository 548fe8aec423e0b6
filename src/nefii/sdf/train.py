"""The geometry stage's optimisation loop: NeuS from images, or an SDF fitted to a given mesh.

Both objectives share one loop (Adam, exponential decay, atomic checkpoints, resume with the
random generator's state, progress bar); they differ in what a step's loss is.
"""
from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import torch
from jaxtyping import Bool, Float
from torch import Tensor
from tqdm import tqdm

from ..camera import pixel_rays
from ..data.scene import SceneData
from ..fit.units import radiance_unit
from ..io.checkpoints import LoadedCheckpoint, save_checkpoint
from ..optim import descend
from .config import GeometryConfig
from .losses import GeometryLoss, geometry_loss, level_set_area, normal_variation
from .model import NeuSModel, render_rays
from .normalization import Normalization


class Objective(Protocol):
    def loss(self, model: NeuSModel, step: int, generator: torch.Generator) -> GeometryLoss: ...


def uniform_in_ball(n: int, generator: torch.Generator, device: torch.device) -> Float[Tensor, "n 3"]:
    d = torch.randn(n, 3, generator=generator, device=device)
    d = d / d.norm(dim=-1, keepdim=True).clamp_min(1e-9)
    return d * torch.rand(n, 1, generator=generator, device=device).pow(1.0 / 3.0)


@dataclass
class ImageObjective:
    """NeuS: render random training rays, compare colours (and opacity with the masks).

    With masks, ``cfg.foreground_rays`` of each batch comes from the masked pixels, the rest from all
    pixels (see :func:`draw_rays`)."""

    cfg: GeometryConfig
    origins: Float[Tensor, "P 3"]
    """normalised ray origins of every training pixel"""
    directions: Float[Tensor, "P 3"]
    rgb: Float[Tensor, "P 3"]
    """in units of ``unit`` of the images' radiance"""
    mask: Bool[Tensor, " P"] | None
    unit: float = 1.0
    """the images' radiance the stage calls 1 (:func:`nefii.fit.units.radiance_unit`)"""
    view_pixels: int = 0
    """pixels per view: pixel ``i`` belongs to view ``i // view_pixels`` (for the model's per-view gains)"""

    def __post_init__(self) -> None:
        self.foreground = None if self.mask is None else self.mask.nonzero().squeeze(-1)
        if self.cfg.exposure == "per_view" and self.view_pixels < 1:
            raise ValueError("exposure = per_view needs view_pixels, the pixels of one view")

    @classmethod
    def from_views(cls, cfg: GeometryConfig, views: SceneData, norm: Normalization, masks: Tensor | None,
                   device: torch.device, unit: float | None = None) -> ImageObjective:
        """Every pixel of ``views`` as a ray in ``norm``'s coordinates; ``masks`` (V, H, W) bool or None.
        The colours are divided by ``unit``, by default the fit's unit of the masked pixels (all pixels without
        masks): the colour loss's ``log1p`` and the colour network's ``softplus`` are absolute, and the corner's
        images times 8 reconstructed with normals 8.9 degrees off (median) against 4.8-5.7 as rendered
        (docs/experiments.md, 2026-11-30)."""
        o, d, rgb = [], [], []
        for v in range(len(views)):
            ov, dv = pixel_rays(views.cameras.c2w[v], views.cameras.K[v], views.height, views.width)
            o.append(norm.to_unit(ov.reshape(-1, 3)).float())
            d.append(dv.reshape(-1, 3).float())
            rgb.append(views.images[v].reshape(-1, 3))
        colours = torch.cat(rgb)
        mask = None if masks is None else masks.reshape(-1)
        if unit is None:
            unit = radiance_unit(colours if mask is None else colours[mask], views.root)
        if unit != 1.0:
            colours = colours / unit
        return cls(cfg, torch.cat(o).to(device), torch.cat(d).to(device), colours.to(device),
                   None if mask is None else mask.to(device), unit, views.height * views.width)

    def loss(self, model: NeuSModel, step: int, generator: torch.Generator) -> GeometryLoss:
        cfg = self.cfg
        i, weight = draw_rays(len(self.origins), self.mask, self.foreground, cfg.batch_rays, cfg.foreground_rays,
                              generator, self.origins.device)
        anneal = min(1.0, step / max(cfg.anneal_end * cfg.steps, 1.0))
        out = render_rays(model, self.origins[i], self.directions[i], cfg, generator, train=True, cos_anneal=anneal)
        if model.gains is not None:                  # the photo is the scene's radiance times its view's gain
            out = dataclasses.replace(out, rgb=out.rgb * model.gains(i // self.view_pixels))
        extra = uniform_in_ball(cfg.batch_rays, generator, self.origins.device)
        _, g_extra, _ = model.sdf.with_gradient(extra, create_graph=True)
        terms = geometry_loss(out, self.rgb[i], None if self.mask is None else self.mask[i], g_extra,
                              cfg.eikonal_weight, cfg.mask_weight, weight)
        if cfg.area_weight > 0:
            u = uniform_in_ball(cfg.area_points, generator, self.origins.device)
            area = level_set_area(model.sdf.sdf(u), cfg.area_sharpness)
            terms = dataclasses.replace(terms, total=terms.total + cfg.area_weight * area)
        if model.gains is not None:
            terms = dataclasses.replace(terms, total=terms.total + model.gains.prior())
        if cfg.normal_smoothness > 0 and step >= cfg.normal_smoothness_start * cfg.steps:
            hit = out.opacity.detach() > 0.5
            surface = (self.origins[i] + out.depth.detach().unsqueeze(-1) * self.directions[i])[hit]
            prior = normal_variation(model.sdf, surface, cfg.normal_radius, generator)
            terms = dataclasses.replace(terms, total=terms.total + cfg.normal_smoothness * prior)
        return terms


def draw_rays(pixels: int, mask: Bool[Tensor, " P"] | None, foreground: Tensor | None, n: int, fraction: float,
              generator: torch.Generator, device: torch.device) -> tuple[Tensor, Tensor | None]:
    """``n`` pixel indices, ``round(fraction n)`` uniform over ``foreground`` (the indices where
    ``mask`` is True; both None without masks) and the rest uniform over all ``pixels``, with each
    one's weight ``(1 / pixels) / q`` under the mixture density ``q`` (so that a weighted mean over
    the batch estimates the mean over all pixels); weights are None when no ray is drawn from the
    foreground."""
    k = round(fraction * n) if foreground is not None and len(foreground) > 0 else 0
    if k == 0:
        return torch.randint(pixels, (n,), generator=generator, device=device), None
    fg = foreground[torch.randint(len(foreground), (k,), generator=generator, device=device)]
    i = torch.cat([fg, torch.randint(pixels, (n - k,), generator=generator, device=device)])
    a = k / n
    q = (1.0 - a) / pixels + a * mask[i].float() / len(foreground)
    return i, (1.0 / pixels) / q


class GeometryTrainer:
    def __init__(self, cfg: GeometryConfig, model: NeuSModel, objective: Objective, device: torch.device) -> None:
        self.cfg, self.model, self.objective, self.device = cfg, model.to(device), objective, device
        table = [p for name, p in model.named_parameters() if name.startswith("sdf.encoding.")]
        table_ids = {id(p) for p in table}
        rest = [p for p in model.parameters() if id(p) not in table_ids]
        groups = [{"params": rest, "lr": cfg.lr_networks}]
        if table:
            groups.append({"params": table, "lr": cfg.lr})
        try:
            self.optimizer = torch.optim.Adam(groups, fused=True)
        except (RuntimeError, TypeError):
            self.optimizer = torch.optim.Adam(groups)
        gamma = cfg.lr_decay ** (1.0 / max(cfg.steps, 1))
        self.scheduler = torch.optim.lr_scheduler.ExponentialLR(self.optimizer, gamma)
        self.generator = torch.Generator(device=device).manual_seed(cfg.seed)
        self.step = 0

    def active_levels(self, step: int) -> float | None:
        """Hash-grid levels in use at ``step`` (see ``GeometryConfig.coarse_to_fine``); None: all."""
        cfg = self.cfg
        levels = len(self.model.sdf.level_weights)
        end = cfg.coarse_to_fine * cfg.steps
        if end <= 0 or step >= end:
            return None
        return cfg.start_levels + (levels - cfg.start_levels) * step / end

    def train_step(self) -> GeometryLoss:
        self.model.sdf.set_active_levels(self.active_levels(self.step))
        terms = self.objective.loss(self.model, self.step, self.generator)
        descend(terms.total, self.optimizer, self.scheduler, f"step {self.step}: geometry loss")
        self.step += 1
        return terms

    def state_dict(self) -> dict:
        return {"step": self.step, "model": self.model.state_dict(), "optimizer": self.optimizer.state_dict(),
                "scheduler": self.scheduler.state_dict(), "generator": self.generator.get_state()}

    def load_state_dict(self, state: dict) -> None:
        self.step = int(state["step"])
        self.model.load_state_dict(state["model"])
        self.optimizer.load_state_dict(state["optimizer"])
        self.scheduler.load_state_dict(state["scheduler"])
        self.generator.set_state(state["generator"].cpu())  # a ByteTensor even for a CUDA generator

    def resume(self, checkpoint: LoadedCheckpoint) -> None:
        """Continue from ``checkpoint`` (see :func:`nefii.io.checkpoints.load_latest_checkpoint`)."""
        checkpoint.restore(self.load_state_dict, "this geometry run")

    def fit(self, folder: Path, progress: bool = True) -> None:
        folder.mkdir(parents=True, exist_ok=True)
        last = time.monotonic()
        bar = tqdm(total=self.cfg.steps, initial=self.step, desc="geometry", unit="step", disable=not progress,
                   dynamic_ncols=True)
        ema = math.nan
        while self.step < self.cfg.steps:
            terms = self.train_step()
            v = terms.total.item()
            ema = v if math.isnan(ema) else 0.95 * ema + 0.05 * v
            bar.set_postfix(loss=f"{ema:.4f}", s=f"{float(self.model.sharpness().detach()):.0f}", refresh=False)
            bar.update(1)
            if time.monotonic() - last >= self.cfg.checkpoint_every_s and self.step < self.cfg.steps:
                save_checkpoint(folder, self.step, self.state_dict())
                last = time.monotonic()
        bar.close()
        self.model.sdf.set_active_levels(None)
        save_checkpoint(folder, self.step, self.state_dict())
