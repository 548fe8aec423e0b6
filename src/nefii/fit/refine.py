"""Geometry refined through the physically based fit (``nefii refine RUN``).

A fit on a reconstruction (``nefii fit --geometry GEO``) holds the SDF of ``nefii geometry`` frozen. Refinement
frees it and optimises it jointly with the material, the light and the cache through the fit's own estimator
and image loss (Eq. 7), IDR-style:

- first hits: Embree on the current zero set's mesh (re-extracted every ``remesh_every`` steps), then Newton
  steps along each ray onto the SDF's zero (:func:`nefii.sdf.implicit.newton_along_ray`);
- the hit differentiated by the implicit function theorem and the shading normal ``grad f / |grad f|`` there
  differentiated twice through the SDF (:func:`~nefii.sdf.implicit.implicit_hit`, :func:`~nefii.sdf.implicit.normal_at`);
- the estimator's directions, densities and secondary rays from the detached normal, the mesh hit and the current
  mesh (:func:`nefii.fit.path_trace.path_trace`'s ``shading_normal``);
- the geometry stage's own objective (NeuS's colour, mask, eikonal, area and normal terms, its colour network
  trained on) kept as an anchor (:class:`GeometryAnchor`): the surface stays where that stage balanced it unless
  the image term moves it. Without one (an SDF fitted to a mesh has no colour network), IDR's silhouette loss on
  the rays the surface gets wrong (a hit outside the mask, a miss inside it), the eikonal term and the geometry
  stage's tangent-plane normal prior stand in; on reconstructions those moved every surface away from the truth
  and opened holes (docs/experiments.md, 2026-11-27).

Gradients dropped (what they bias): visibility and the secondary hits are not differentiated (a shadow's edge
or an occluder's position does not move the surface: a lid over a hollow is not opened by the shading of the
hollow's inside, only by the masks and by the normals it shows); the material lookup and the secondary rays
start at the mesh's hit, so the hit's position reaches the loss only through the normal evaluated there;
the sampling densities are constants of the gradient (the estimator's gradient is that of the integrand at
fixed samples, unbiased for the image term's expectation).
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Annotated

import numpy as np
import torch
import trimesh
from jaxtyping import Bool, Float
from torch import Tensor, nn

from ..config_tools import Range, validate
from ..data.scene import SceneData
from ..optim import descend
from ..raycast import MeshGeometry, Rays
from ..sdf.extract import extract_mesh
from ..sdf.implicit import implicit_hit, newton_along_ray, normal_at, silhouette_loss
from ..sdf.losses import normal_variation
from ..sdf.model import NeuSModel
from ..sdf.networks import SDFNetwork
from ..sdf.normalization import Normalization
from ..sdf.train import ImageObjective
from ..sdf.volume import sphere_bounds
from .config import FitConfig
from .losses import LossTerms, SmoothnessPrior, observed_loss, smoothness
from .model import NeFIIModel, decode_material
from .path_trace import SurfacePoints, path_trace
from .pixels import view_rays
from .trainer import transport_of


@dataclass
class RefineConfig:
    steps: Annotated[int, Range(1)] = 800
    """refinement steps"""
    batch_pixels: Annotated[int, Range(1)] = 1024
    """training pixels per step (inside and outside the masks)"""
    lr_sdf: Annotated[float, Range(0, 10)] = 5.0
    """the SDF's learning rates (its hash table's, its MLP's; with an anchor, its colour network's too) as a
    multiple of the rates the geometry stage ended at (at the stage's starting rates, without an anchor, the SDF's
    MLP random-walked and the bowl's surface degraded)"""
    lr_fields: Annotated[float, Range(0, 10)] = 1.0
    """the material's, cache's and light's learning rates as a multiple of the rates the fit ended at"""
    lr_decay: Annotated[float, Range(0, 1, lo_open=True)] = 0.1
    """learning rates fall exponentially to this fraction at the last step"""
    anchor: Annotated[float, Range(0)] = 0.1
    """weight of the geometry stage's own objective (:class:`GeometryAnchor`) against the image term's 1"""
    eikonal: Annotated[float, Range(0)] = 0.1
    """without an anchor: weight of ``(|grad f| - 1)^2`` at the hits and at random points in the unit sphere"""
    silhouette: Annotated[float, Range(0)] = 1.0
    """without an anchor: weight of IDR's mask loss (with masks only)"""
    silhouette_samples: Annotated[int, Range(2, 1024)] = 32
    """depths per ray at which the SDF's minimum is taken for the mask loss"""
    silhouette_sharpness: Annotated[float, Range(0, lo_open=True)] = 50.0
    """``alpha`` of the mask loss's ``sigmoid(-alpha min f)``, in 1 / normalised units (IDR: 50)"""
    normal_smoothness: Annotated[float, Range(0)] = 0.01
    """without an anchor: weight of the geometry stage's tangent-plane normal prior at the hits (``nefii geometry``
    uses 0.05, which resists the shading's pull: a sphere's missing bump grew half as fast, tests/test_refine.py)"""
    normal_radius: Annotated[float, Range(0, 1)] = 0.02
    """its tangent step, in normalised units"""
    remesh_every: Annotated[int, Range(1)] = 200
    """steps between re-extractions of the mesh that first hits start from and secondary rays are cast against"""
    remesh_resolution: Annotated[int, Range(8, 2048)] = 128
    """marching-cubes resolution of those meshes (Newton steps take first hits the rest of the way)"""
    mesh_resolution: Annotated[int, Range(8, 2048)] = 256
    """marching-cubes resolution of the refined mesh written at the end"""
    newton_iterations: Annotated[int, Range(0, 64)] = 4
    """Newton steps along a ray from the mesh's hit to the SDF's zero"""
    seed: Annotated[int, Range(0, 2**63 - 1)] = 0
    """seeds pixel batches and samples"""
    checkpoint_every_s: Annotated[float, Range(0)] = 120.0
    """seconds between checkpoints"""
    threads: Annotated[int, Range(0, 4096)] = 0
    """CPU threads for torch (0: the cores this process may use)"""

    def __post_init__(self) -> None:
        validate(self)


@dataclass(frozen=True)
class TrainingRays:
    """Every training pixel's camera ray (world), colour and mask."""

    origins: Float[Tensor, "P 3"]
    directions: Float[Tensor, "P 3"]
    rgb: Float[Tensor, "P 3"]
    mask: Bool[Tensor, " P"] | None
    """the object masks; None without masks"""
    usable: Bool[Tensor, " P"]
    """not clipped (their colour may enter the image loss)"""

    @staticmethod
    def of(scene: SceneData) -> "TrainingRays":
        o, d = [], []
        for v in range(len(scene)):
            ov, dv = view_rays(scene, v)
            o.append(ov.reshape(-1, 3))
            d.append(dv.reshape(-1, 3))
        usable = torch.ones(len(scene) * scene.height * scene.width, dtype=torch.bool) if scene.clipped is None \
            else ~scene.clipped.reshape(-1)
        return TrainingRays(torch.cat(o), torch.cat(d), scene.images.reshape(-1, 3).float(),
                            None if scene.masks is None else scene.masks.reshape(-1), usable)

    def __len__(self) -> int:
        return len(self.origins)


@dataclass(frozen=True)
class GeometryAnchor:
    """The geometry stage's objective as that stage ended, on the model it trained (whose SDF is refined)."""

    model: NeuSModel
    objective: ImageObjective
    step: int
    """the stage's last step: its annealing and its priors' schedules as they ended"""

    def loss(self, generator: torch.Generator) -> Tensor:
        return self.objective.loss(self.model, self.step, generator).total

    def networks(self) -> list[nn.Parameter]:
        """What the anchor trains besides the SDF."""
        return [p for name, p in self.model.named_parameters() if not name.startswith("sdf.")]


@dataclass(frozen=True)
class RefineTerms:
    total: Tensor
    image: LossTerms | None
    """Eq. 7 on the pixels whose rays hit (None when no ray of the batch did)"""
    anchor: Tensor
    silhouette: Tensor
    eikonal: Tensor
    normal: Tensor
    hits: int


class Refiner:
    """The SDF, the material, the cache and the light optimised together (see the module's docstring)."""

    def __init__(self, cfg: RefineConfig, fit_cfg: FitConfig, model: NeFIIModel, sdf: SDFNetwork, norm: Normalization,
                 rays: TrainingRays, normal_sigma: float, lookup_sigma: float, sdf_rates: tuple[float, float],
                 device: torch.device, anchor: GeometryAnchor | None = None) -> None:
        """``sdf_rates``: the Adam rates of the SDF's hash table and of the rest of the stage's networks (the SDF's
        MLP; with an anchor, the colour network, sharpness and background too) as the geometry stage ended
        (``cfg.lr_sdf`` scales them). ``anchor``: the geometry stage's objective on the model whose SDF is ``sdf``."""
        if anchor is not None and anchor.model.sdf is not sdf:
            raise ValueError("the anchor's model must hold the SDF being refined")
        self.cfg, self.fit_cfg, self.model, self.sdf, self.norm, self.rays = cfg, fit_cfg, model, sdf, norm, rays
        self.anchor = anchor
        self.normal_sigma, self.lookup_sigma, self.device = normal_sigma, lookup_sigma, device
        sdf.requires_grad_(True).train()
        final = fit_cfg.lr_decay * cfg.lr_fields
        groups = model.param_groups(fit_cfg.lr * final, fit_cfg.lr_light * final, fit_cfg.lr_light_shape * final)
        table = list(sdf.encoding.parameters())                     # a hash grid's table (a Fourier encoding: none)
        ids = {id(p) for p in table}
        groups.append({"params": [p for p in sdf.parameters() if id(p) not in ids], "lr": sdf_rates[1] * cfg.lr_sdf})
        if table:
            groups.append({"params": table, "lr": sdf_rates[0] * cfg.lr_sdf})
        if anchor is not None:
            networks = anchor.networks()
            for p in networks:
                p.requires_grad_(True)
            anchor.model.train()
            groups.append({"params": networks, "lr": sdf_rates[1] * cfg.lr_sdf})
        self.optimizer = torch.optim.Adam(groups)
        self.scheduler = torch.optim.lr_scheduler.ExponentialLR(self.optimizer, cfg.lr_decay ** (1.0 / cfg.steps))
        self.generator = torch.Generator(device=device).manual_seed(cfg.seed)
        self.transport = transport_of(fit_cfg)
        self.mesh: MeshGeometry | None = None
        """set with :attr:`prior` by :meth:`_use_mesh` at the first step"""
        self.prior: SmoothnessPrior
        self.step = 0

    # ---- the mesh the rays are cast against
    def zero_set(self, resolution: int) -> trimesh.Trimesh:
        """The SDF's zero set now, in world coordinates (marching cubes at ``resolution``)."""
        return extract_mesh(self.sdf, self.norm, resolution)

    def _use_mesh(self, vertices: np.ndarray, faces: np.ndarray) -> None:
        """Cast rays against this mesh from now on (vertex normals smoothed as the run's source says), with the
        albedo prior at the weight the fit ended with, on its scale."""
        self._arrays = (np.asarray(vertices, dtype=np.float64), np.asarray(faces, dtype=np.int64))
        self.mesh = MeshGeometry.smoothed(*self._arrays, self.normal_sigma, self.lookup_sigma)
        fit_cfg = self.fit_cfg
        self.prior = SmoothnessPrior(fit_cfg.smooth_albedo * fit_cfg.smooth_albedo_end,
                                     fit_cfg.smooth_radius * self.mesh.scale)

    # ---- one step
    def loss(self) -> RefineTerms:
        cfg, fit_cfg, model, sdf, g = self.cfg, self.fit_cfg, self.model, self.sdf, self.generator
        if self.mesh is None or self.step % cfg.remesh_every == 0:
            zero_set = self.zero_set(cfg.remesh_resolution)
            self._use_mesh(zero_set.vertices, zero_set.faces)
        idx = torch.randint(len(self.rays), (cfg.batch_pixels,), generator=g, device=self.device)
        o_w, d = self.rays.origins[idx], self.rays.directions[idx]
        mask = None if self.rays.mask is None else self.rays.mask[idx]
        hit = self.mesh.intersect(Rays(o_w, d))
        o_u = self.norm.to_unit(o_w)
        zero = o_u.new_zeros(())

        # ---- first hits on the SDF's zero
        valid = hit.valid.clone()
        t_u = torch.where(valid, hit.t / self.norm.radius, torch.zeros_like(hit.t))
        if valid.any():
            t_new, residual = newton_along_ray(sdf, o_u[valid], d[valid], t_u[valid], cfg.newton_iterations)
            t_u[valid] = t_new
            valid[valid.clone()] = (residual < 1e-3) & (t_new > 0)
        obj = valid & self.rays.usable[idx]
        if mask is not None:
            obj = obj & mask
        image, normal_prior, eik_hits = None, zero, zero
        hits = int(obj.sum())
        if hits:
            x_u = implicit_hit(sdf, o_u[obj], d[obj], t_u[obj])
            n, grad = normal_at(sdf, x_u)
            eik_hits = (grad.norm(dim=-1) - 1.0).square().mean()
            pts = SurfacePoints(hit.position[obj], n.detach(), hit.geometric_normal[obj], -d[obj],
                                hit.lookup_normal[obj])
            material = decode_material(model, pts.position, pts.lookup_normal)
            traced = path_trace(model, self.mesh, pts, material, fit_cfg.num_samples, g, self.transport,
                                shading_normal=n)
            smooth = None
            if self.prior.active:
                near = self.prior.neighbours(pts.position, pts.normal, g)
                smooth = smoothness(material.albedo, decode_material(model, near, pts.lookup_normal).albedo,
                                    self.prior.weight)
            empty = pts.position.new_zeros(0, 3)
            image = observed_loss(traced, model.cache(pts.position, pts.normal, pts.wo), self.rays.rgb[idx][obj],
                                  empty, empty, fit_cfg.tonemap, fit_cfg.loss, fit_cfg.beta1, 0.0, smooth)
            if self.anchor is None and cfg.normal_smoothness > 0:
                normal_prior = normal_variation(sdf, x_u.detach(), cfg.normal_radius, g)
        image_total = image.total if image is not None else zero
        if self.anchor is not None:
            anchor = self.anchor.loss(g)
            return RefineTerms(image_total + cfg.anchor * anchor, image, anchor, zero, zero, zero, hits)

        # ---- without an anchor: silhouettes and the eikonal term
        sil = zero
        if mask is not None and cfg.silhouette > 0:
            # IDR's rule: only rays the surface gets wrong (a hit outside the mask, a miss inside it); on a ray that
            # hits inside the mask, the loss would keep pushing min f down and thicken every thin wall
            near, far, through = sphere_bounds(o_u, d)
            through = through & ~(valid & mask)
            if through.any():
                sil = silhouette_loss(sdf, o_u[through], d[through], near[through], far[through], mask[through],
                                      cfg.silhouette_samples, cfg.silhouette_sharpness, g)
        u = torch.randn(cfg.batch_pixels // 2, 3, generator=g, device=self.device)
        u = u / u.norm(dim=-1, keepdim=True) * torch.rand(len(u), 1, generator=g, device=self.device) ** (1 / 3)
        _, grad_free, _ = sdf.with_gradient(u, create_graph=True)
        eik = 0.5 * (eik_hits + (grad_free.norm(dim=-1) - 1.0).square().mean())
        total = image_total + cfg.silhouette * sil + cfg.eikonal * eik + cfg.normal_smoothness * normal_prior
        return RefineTerms(total, image, zero, sil, eik, normal_prior, hits)

    def train_step(self) -> RefineTerms:
        terms = self.loss()
        descend(terms.total, self.optimizer, self.scheduler, f"refinement step {self.step}: the loss")
        self.step += 1
        return terms

    # ---- checkpoints
    def state_dict(self) -> dict:
        return {"step": self.step, "model": self.model.state_dict(), "sdf": self.sdf.state_dict(),
                "optimizer": self.optimizer.state_dict(), "scheduler": self.scheduler.state_dict(),
                "generator": self.generator.get_state(), "config": dataclasses.asdict(self.cfg),
                "mesh": None if self.mesh is None else tuple(torch.from_numpy(a) for a in self._arrays),
                "anchor": None if self.anchor is None else self.anchor.model.state_dict()}

    def load_state_dict(self, state: dict) -> None:
        self.step = int(state["step"])
        self.model.load_state_dict(state["model"])
        self.sdf.load_state_dict(state["sdf"])
        if self.anchor is not None:
            self.anchor.model.load_state_dict(state["anchor"])
        self.optimizer.load_state_dict(state["optimizer"])
        self.scheduler.load_state_dict(state["scheduler"])
        self.generator.set_state(state["generator"])
        mesh = state.get("mesh")                 # the mesh the rays were cast against: a resumed run goes on the same
        if mesh is not None:
            self._use_mesh(mesh[0].numpy(), mesh[1].numpy())
