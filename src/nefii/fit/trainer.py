"""The training loop: alternate Eq. 7 and Eq. 8, warm up roughness, checkpoint, resume.

The loop asks small policy objects what to do at each step (:mod:`nefii.fit.policies`) and
keeps every source of randomness in one generator, whose state is checkpointed with the
model, the optimiser and the secondary-hit buffer: a resumed run continues the same sequence.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import torch
from jaxtyping import Bool, Float
from torch import Tensor
from tqdm import tqdm

from ..raycast.base import Geometry
from ..io.checkpoints import save_checkpoint
from ..render.brdf import Material
from ..fields.environment import SGEnvironment
from ..render.sg import sg_detach_sharper, sg_eval, sg_integral
from .config import FitConfig, config_to_dict
from .distributed import DistContext, any_rank, average_gradients
from .exposure import ViewGains
from .light_init import beyond_glow, sharpen_lobe
from .light_prior import light_coverage, unseen_light_prior
from .light_solve import (average_quadratic, background_quadratic, linear_term, lobe_design, pixel_quadratic,
                          solve_nonnegative)
from .losses import (Gains, LossTerms, SecondaryHitBuffer, SmoothnessPrior, observed_loss, smoothness, tonemap_slope,
                     unobserved_loss)
from .model import NeFIIModel, decode_material
from .path_trace import (PathTraced, SurfacePoints, Transport, environment_where, path_trace, sample_directions,
                         two_point_pair)
from .pixels import FOOTPRINT_GRID, Pixels
from .policies import Alternation, LightSolveSchedule, PriorFade, RoughnessWarmup
from .units import rescale_radiance

LIGHT_SOLVE_SAMPLES = 32
"""estimator samples per pixel when the light's amplitudes are solved (the solve is rare: its noise is cheap
to cut)"""
LIGHT_SOLVE_CHUNK = 1024
"""pixels per pass of the solve (bounds its memory)"""
AMPLITUDE_MIN = 1e-4
"""the least amplitude a solved lobe keeps (its log is the parameter)"""


def learned_part(material: Material, learn: str) -> Material:
    """``material`` with the gradient stopped on what a loss is not to train: ``all`` (nothing stopped),
    ``albedo`` (the roughness stopped) or ``none`` (both stopped)."""
    if learn == "all":
        return material
    if learn not in ("albedo", "none"):
        raise ValueError(f"unknown material part {learn!r} (all | albedo | none)")
    albedo = material.albedo if learn == "albedo" else material.albedo.detach()
    return Material(albedo, material.roughness.detach(), material.brdf)


def transport_of(cfg: FitConfig) -> Transport:
    """The light paths a run's estimator follows (training, eval and previews alike)."""
    return Transport(indirect=cfg.indirect, visibility=cfg.visibility, ray_offset=cfg.ray_offset)


class NonFiniteLoss(RuntimeError):
    """A step produced NaN/inf: reported, never saved."""


@dataclass
class StepLog:
    step: int
    kind: str
    """``observed`` or ``unobserved``"""
    terms: LossTerms


class Trainer:
    def __init__(self, cfg: FitConfig, model: NeFIIModel, geometry: Geometry, pixels: Pixels,
                 device: torch.device, dist: DistContext = DistContext(), num_views: int = 1,
                 metered: Tensor | None = None, sun_lobe: int | None = None, radiance_unit: float = 1.0) -> None:
        """``num_views``: the training views (``exposure = per_view`` learns a gain for each); ``metered``: their
        EXIF exposures, where the gains start (:class:`nefii.fit.exposure.ViewGains`); ``sun_lobe``: the SG lobe
        the light's start put on a searched sun, sharpened to ``light.sharpness_init_peak`` when the roughness
        warm-up ends (:mod:`nefii.fit.light_init`); ``radiance_unit``: the images' radiance that ``pixels``' colours
        are in units of (:mod:`nefii.fit.units`), kept in checkpoints so a resumed fit reads its model in it."""
        self.cfg, self.model, self.geometry, self.pixels, self.device = cfg, model.to(device), geometry, pixels, device
        self.dist = dist
        self.gains = ViewGains(num_views, metered).to(device) if cfg.exposure == "per_view" else None
        self.params = [p for p in self.model.parameters() if p.requires_grad]   # a frozen SDF's are not
        groups = model.param_groups(cfg.lr, cfg.lr_light, cfg.lr_light_shape)
        if self.gains is not None:  # a gain is a light level: it moves at the light's rate
            self.params.append(self.gains.log_gain)
            groups.append({"params": [self.gains.log_gain], "lr": cfg.lr_light})
        try:  # the fused kernel is ~5x faster on the CPU for the large hash-grid tables
            self.optimizer = torch.optim.Adam(groups, fused=True)
        except (RuntimeError, TypeError):
            self.optimizer = torch.optim.Adam(groups)
        gamma = cfg.lr_decay ** (1.0 / max(cfg.steps, 1))
        self.scheduler = torch.optim.lr_scheduler.ExponentialLR(self.optimizer, gamma)
        self.generator = torch.Generator(device=device).manual_seed(cfg.seed + 1000 * dist.rank)
        self.buffer = SecondaryHitBuffer(cfg.secondary_buffer)
        self.warmup = RoughnessWarmup(int(round(cfg.roughness_warmup * cfg.steps)))
        self.alternation = Alternation(cfg.unobserved_every, cfg.unobserved)
        self.transport = transport_of(cfg)
        self.prior = SmoothnessPrior(cfg.smooth_albedo, cfg.smooth_radius * geometry.scale)
        self.prior_fade = PriorFade(self.warmup.steps, cfg.steps, cfg.smooth_albedo_end)
        self.sky_term = len(pixels.bg_dirs) > 0 and cfg.beta2 > 0 and cfg.background_pixels > 0
        """whether Eq. 7's third term (and the light solve's background rows) are formed"""
        self.coverage = (light_coverage(pixels.points, geometry, cfg.ray_offset * geometry.scale, cfg.seed)
                         if cfg.light_prior > 0 or self.sky_term else None)
        """how much the training points see each direction: the light prior's and the sky term's weights"""
        solves = cfg.light.kind == "sg" and cfg.loss == "l2_pair"     # what light_solve's quadratic is
        self.light_solve = LightSolveSchedule(cfg.light_solve_every if solves else 0, cfg.steps)
        self.sun_lobe = sun_lobe
        self.radiance_unit = radiance_unit
        self.sees_sky = bool(pixels.footprint_sky.any())
        """whether some footprint position sees past the object (edge pixels where the background is visible)"""
        self.has_edges = bool(pixels.edge.any())
        """whether some object pixel mixes object and environment (the cache's term then reads the others only)"""
        self.solid_pixels = pixels.solid.nonzero()[:, 0]
        """the object pixels the silhouette does not cross: the light solve's"""
        self.step = 0

    # ---- one step
    def _observed_batch(self) -> Pixels:
        px, g = self.pixels, self.generator
        i = torch.randint(len(px.points), (self.cfg.batch_pixels,), generator=g, device=self.device)
        nb = min(self.cfg.background_pixels, len(px.bg_dirs))
        j = torch.randint(max(len(px.bg_dirs), 1), (nb,), generator=g, device=self.device)
        return px.select(i, j[self._sky_usable(px.bg_dirs[j])] if nb else j)

    @torch.no_grad()
    def _sky_usable(self, dirs: Float[Tensor, "Q 3"]) -> Bool[Tensor, " Q"]:
        """Which background directions Eq. 7's third term and the light solve read: all, except in the glow of the
        sun's lobe at its current sharpness (wide through the warm-up, sharp after it; :mod:`nefii.fit.light_init`)."""
        env = self.model.env
        if self.sun_lobe is None or not isinstance(env, SGEnvironment):
            return torch.ones(len(dirs), dtype=torch.bool, device=dirs.device)
        sg = env()
        return beyond_glow(dirs, sg.axis[self.sun_lobe], float(sg.sharpness[self.sun_lobe]))

    def _sky_weight(self, dirs: Float[Tensor, "Q 3"]) -> Float[Tensor, " Q"] | None:
        """Each background pixel's weight in Eq. 7's third term and the light solve: how much the object sees its
        direction (:meth:`LightCoverage.seen`). The camera's view of the sky pins the light the object is lit by;
        most of a capture's background is ground the object, standing on it, hardly sees, and fitting that spent
        the lobes the object's shading needs (docs/experiments.md, 2026-12-04). None: no coverage, weight 1."""
        return None if self.coverage is None else self.coverage.seen(dirs)

    def _trace(self, pts: SurfacePoints, rough: float | None, learn: str = "all",
               environment: Callable[[Tensor], Tensor] | None = None, num_samples: int | None = None):
        """The material at ``pts`` and the estimator's colour there (Eq. 2-4); ``learn`` says what of the material
        the estimate's gradient reaches (``all``, ``albedo`` or ``none``, as ``FitConfig.unobserved_material``).
        ``environment``: see ``path_trace``."""
        material = learned_part(decode_material(self.model, pts.position, pts.lookup_normal, rough), learn)
        traced = path_trace(self.model, self.geometry, pts, material, num_samples or self.cfg.num_samples,
                            self.generator, self.transport, environment=environment)
        return material, traced

    def _trace_footprint(self, batch: Pixels, rough: float | None) -> tuple[SurfacePoints, Material, PathTraced]:
        """Each pixel of ``batch`` estimated at two of its footprint positions drawn independently, half the
        samples at each: their mean is an estimate of the pixel's average over its footprint, as the image
        records it, and the two are the independent pair the ``l2_pair`` loss needs. A position past the
        silhouette sees the environment along its ray (:func:`environment_where`). Returns the first position's
        points and material (for the cache's term and the priors) and the pair's estimate."""
        B, F = len(batch.points), len(FOOTPRINT_GRID)
        first, sky1 = batch.at_footprint(torch.randint(F, (B,), generator=self.generator, device=self.device))
        second, sky2 = batch.at_footprint(torch.randint(F, (B,), generator=self.generator, device=self.device))
        pts = SurfacePoints.cat([first, second])
        material, traced = self._trace(pts, rough, num_samples=max(self.cfg.num_samples // 2, 1))
        if self.sees_sky:
            traced = environment_where(traced, torch.cat([sky1, sky2]), self.model.env.radiance(-pts.wo))
        return first, Material(material.albedo[:B], material.roughness[:B], material.brdf), two_point_pair(traced, B)

    def _consistency_light(self) -> Callable[[Tensor], Tensor] | None:
        """The environment's radiance as Eq. 8 trains it (``FitConfig.unobserved_light``); None: as it is."""
        env = self.model.env
        if self.cfg.unobserved_light == "all" or not isinstance(env, SGEnvironment):
            return None
        limit = self.model.cache.max_lobe_sharpness
        return lambda w: sg_eval(w, sg_detach_sharper(env(), limit))

    @torch.no_grad()
    def solve_light(self, rough: float | None) -> None:
        """The SG amplitudes set to Eq. 7's minimiser given the rest of the model (:mod:`nefii.fit.light_solve`),
        on ``light_solve_pixels`` training pixels and background pixels; Adam's moments for them restart."""
        cfg, px, model, g = self.cfg, self.pixels, self.model, self.generator
        env = model.env
        sg = env()                                    # no gradient: solve_light runs under no_grad
        solid = self.solid_pixels
        idx = solid[torch.randint(len(solid), (cfg.light_solve_pixels,), generator=g, device=self.device)]
        q, sampler = None, env.light_sampler()
        for part in idx.split(LIGHT_SOLVE_CHUNK):
            pts = px.points[part]
            material = decode_material(model, pts.position, pts.lookup_normal, rough)
            samples = sample_directions(pts, material, sampler, LIGHT_SOLVE_SAMPLES, g)
            design = lobe_design(pts, material, samples, sg, self.geometry, model.cache, self.transport)
            gain = None if self.gains is None else self.gains(px.view[part])
            term = pixel_quadratic(design, px.rgb[part], tonemap_slope(px.rgb[part], cfg.tonemap), gain)
            q = term.scaled(len(part) / len(idx)) if q is None else q + term.scaled(len(part) / len(idx))
        j = None
        if self.sky_term:
            j = torch.randint(len(px.bg_dirs), (cfg.light_solve_pixels,), generator=g, device=self.device)
            j = j[self._sky_usable(px.bg_dirs[j])]
        if j is not None and len(j):            # none left: every pixel drawn lies in the sun lobe's glow
            gain = None if self.gains is None else self.gains(px.bg_view[j])
            weight = tonemap_slope(px.bg_rgb[j], cfg.tonemap)
            seen = self._sky_weight(px.bg_dirs[j])
            if seen is not None:                # the solve squares the weight
                weight = weight * seen.sqrt()[:, None]
            q = q + background_quadratic(sg, px.bg_dirs[j], px.bg_rgb[j], weight, gain).scaled(cfg.beta2)
        if self.coverage is not None and cfg.light_prior > 0:
            integral = sg_integral(sg.sharpness)
            energy = float((sg.amplitude.mean(-1) * integral).sum())
            q = q + linear_term(cfg.light_prior * self.coverage.at(sg.axis) * integral / max(energy, 1e-12))
        q = average_quadratic(q, self.dist)
        x = solve_nonnegative(q, sg.amplitude.T)
        env.log_amplitude.copy_(x.T.to(env.log_amplitude).clamp_min(AMPLITUDE_MIN).log())
        self.optimizer.state[env.log_amplitude] = {}

    def train_step(self) -> StepLog:
        cfg, step, model = self.cfg, self.step, self.model
        rough = self.warmup.override(step)
        if self.sun_lobe is not None and step == self.warmup.steps and isinstance(model.env, SGEnvironment):
            sharpen_lobe(model.env, self.sun_lobe, cfg.light.sharpness_init_peak)
        if self.light_solve.due(step):
            self.solve_light(rough)
        if self.alternation.unobserved(step) and len(self.buffer) > 0:
            # ---- Eq. 8: secondary hits drawn from the buffer, path-traced against the cache there
            pts = self.buffer.sample(cfg.unobserved_points, self.generator)
            _, traced = self._trace(pts, rough, cfg.unobserved_material, environment=self._consistency_light())
            terms = unobserved_loss(traced, model.cache(pts.position, pts.normal, pts.wo), cfg.tonemap, cfg.loss)
            kind = "unobserved"
        else:
            # ---- Eq. 7: a batch of observed pixels and background pixels
            batch = self._observed_batch()
            pts, material, traced = self._trace_footprint(batch, rough)
            smooth = None
            if self.prior.active:
                near = self.prior.neighbours(pts.position, pts.normal, self.generator)
                smooth = smoothness(material.albedo, decode_material(model, near, pts.lookup_normal, rough).albedo,
                                    self.prior.weight * self.prior_fade.factor(step))
            light = None
            if self.coverage is not None and cfg.light_prior > 0:
                light = unseen_light_prior(*model.env.energy_atoms(), self.coverage, cfg.light_prior)
            gains = None
            if self.gains is not None:
                gains = Gains(self.gains(batch.view), self.gains(batch.bg_view), self.gains.prior())
            terms = observed_loss(traced, model.cache(pts.position, pts.normal, pts.wo), batch.rgb,
                                  model.env.radiance(batch.bg_dirs), batch.bg_rgb, cfg.tonemap, cfg.loss,
                                  cfg.beta1, cfg.beta2, smooth, light, gains,
                                  cache_rows=batch.solid if self.has_edges else None,
                                  bg_weight=self._sky_weight(batch.bg_dirs))
            self.buffer.add(traced.secondary)
            kind = "observed"
        if any_rank(not bool(torch.isfinite(terms.total)), self.dist, self.device):
            raise NonFiniteLoss(f"step {step}: {kind} loss is not finite ({terms.total.item()} on rank {self.dist.rank})")
        self.optimizer.zero_grad(set_to_none=True)
        terms.total.backward()
        average_gradients(self.params, self.dist)
        self.optimizer.step()
        self.scheduler.step()
        self.step += 1
        return StepLog(step, kind, terms)

    # ---- checkpoints
    def state_dict(self) -> dict:
        return {
            "step": self.step,
            "model": self.model.state_dict(),
            "optimizer": self.optimizer.state_dict(),
            "scheduler": self.scheduler.state_dict(),
            "generator": self.generator.get_state(),
            "buffer": self.buffer.state_dict(),
            "config": config_to_dict(self.cfg),
            "gains": None if self.gains is None else self.gains.state_dict(),
            "sun_lobe": self.sun_lobe,
            "radiance_unit": self.radiance_unit,
        }

    def load_state_dict(self, state: dict) -> None:
        self.step = int(state["step"])
        self.sun_lobe = state.get("sun_lobe")                     # checkpoints from before the sun search: none
        self.model.load_state_dict(state["model"])
        saved = float(state.get("radiance_unit", 1.0))           # checkpoints from before the unit: the images'
        if saved != self.radiance_unit:
            rescale_radiance(self.model, saved / self.radiance_unit)
        if self.gains is not None:
            self.gains.load_state_dict(state["gains"])
        self.optimizer.load_state_dict(state["optimizer"])
        self.scheduler.load_state_dict(state["scheduler"])
        if self.dist.rank == 0:
            self.generator.set_state(state["generator"].cpu())  # a ByteTensor even for a CUDA generator
        else:  # other ranks' streams are not saved: restart them deterministically from the step
            self.generator.manual_seed(self.cfg.seed + 1000 * self.dist.rank + 7919 * self.step)
        self.buffer.load_state_dict(state["buffer"], self.device)

    def save_checkpoint(self, folder: Path) -> Path | None:
        """Rank 0 writes ``step_XXXXXXX.pt`` atomically and keeps the last two."""
        if not self.dist.is_main:
            return None
        return save_checkpoint(folder, self.step, self.state_dict())

    # ---- the loop
    def fit(self, checkpoint_dir: Path, log=None, progress: bool = True, preview=None) -> None:
        """Train to ``cfg.steps``, checkpointing every ``checkpoint_every_s`` seconds and at the end;
        ``preview(step)`` is called every ``cfg.preview_every`` steps on rank 0."""
        last_ckpt = time.monotonic()
        bar = tqdm(total=self.cfg.steps, initial=self.step, desc="fit", unit="step",
                   disable=not progress or not self.dist.is_main, dynamic_ncols=True)
        ema = math.nan
        while self.step < self.cfg.steps:
            rec = self.train_step()
            if rec.kind == "observed":
                v = rec.terms.render.item()
                ema = v if math.isnan(ema) else 0.95 * ema + 0.05 * v
                bar.set_postfix(loss=f"{ema:.4f}", refresh=False)
            if log is not None and self.dist.is_main:
                log(rec)
            if preview is not None and self.dist.is_main and self.cfg.preview_every and \
                    self.step % self.cfg.preview_every == 0:
                preview(self.step)
            bar.update(1)
            if time.monotonic() - last_ckpt >= self.cfg.checkpoint_every_s and self.step < self.cfg.steps:
                self.save_checkpoint(checkpoint_dir)  # rank 0 only
                last_ckpt = time.monotonic()
        bar.close()
        self.save_checkpoint(checkpoint_dir)
