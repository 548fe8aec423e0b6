"""What a fit is, in one place: the geometry source, the training pixels' first hits, the model, the light
initialisation and resuming. ``nefii fit``, the benchmarks and the tests all start a fit through
:func:`prepare_fit`, so they measure the same recipe."""
from __future__ import annotations

import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import torch
from torch import Tensor

from ..data import load_scene
from ..data.downscale import training_images
from ..data.fingerprint import DataFingerprint, fingerprint, require_same
from ..data.scene import SceneData
from ..io.checkpoints import LoadedCheckpoint
from ..raycast import MeshGeometry
from ..raycast.base import Geometry
from .alignment import check_alignment, check_winding
from .backdrop import without_backdrop
from .build import build_model
from .config import FitConfig
from .distributed import DistContext
from .exposure import metered_log_gains, without_gains
from .geometry_source import GeometrySource, adapt_to_source, resolve_source
from .light_init import SGInit, estimate_light, set_sg_parameters, sg_from_light, sky_sun
from .model import NeFIIModel
from .pixels import Pixels, background_clipping, first_hits
from .trainer import Trainer
from .units import radiance_unit


@dataclass
class FitSession:
    """Everything a fit's loop and its outputs need; ``trainer.fit`` runs it."""

    config: FitConfig
    """the config as it applies to this geometry (:func:`adapt_to_source`)"""
    scene: SceneData
    """the training split"""
    source: GeometrySource
    geometry: Geometry
    box: tuple[Tensor, Tensor]
    """corners of the geometry's bounding box (CPU)"""
    pixels: Pixels
    """the training pixels, their colours in the fit's unit of radiance"""
    trainer: Trainer
    radiance_unit: float
    """the images' radiance the fit calls 1 (:mod:`nefii.fit.units`): what the written model is scaled back by"""
    data: DataFingerprint
    """what the fit is on (the run's manifest records it)"""

    @property
    def model(self) -> NeFIIModel:
        return self.trainer.model


def describe_geometry(source: GeometrySource, geometry: Geometry, cfg: FitConfig, feature_dim: int) -> str:
    """One line: what the rays are cast against."""
    if isinstance(geometry, MeshGeometry):
        what = f"mesh {source.mesh} ({len(geometry.faces)} triangles)"
    else:
        what = f"SDF of {source.folder}, sphere-traced, feature vector of {feature_dim}"
    if source.folder is not None:
        what += (f" (a reconstruction: material offset {cfg.material_offset:g}, normals smoothed to "
                 f"{source.normal_sigma:g} of the diagonal, the lookup's to {source.lookup_sigma:g})")
    return what


def shading_start(cfg: FitConfig) -> bool:
    """Whether the fit's light starts from the pixels' shading (:func:`initialise_light`)."""
    return cfg.light.kind == "sg" and cfg.light.init == "shading"


def initialise_light(model: NeFIIModel, pixels: Pixels, geometry: Geometry, cfg: FitConfig,
                     metered: Tensor | None = None, seen_sun: Tensor | None = None) -> SGInit:
    """The SG lobes from the pixels' diffuse shading and shadows, as set in ``model``, for a config whose light
    starts there (:func:`shading_start`). With per-view gains (``exposure = per_view``) and the
    views' EXIF exposures ``metered`` (V,), the colours are read with the gains' start divided out, as the fit
    will render them: a view shot a stop brighter is not a brighter sky where it looks (on leaning's phone
    capture the searched sun 17 -> 10 degrees from the truth; docs/experiments.md, 2026-11-29). ``seen_sun``: a
    light source the background sees (:func:`nefii.fit.light_init.sky_sun`), used where the shading shows no
    peak. Pixels the silhouette crosses are left out: their colour is no one surface's shading."""
    solid = pixels.solid
    pts, rgb = pixels.points[solid], pixels.rgb[solid]
    if metered is not None and cfg.exposure == "per_view":
        rgb = without_gains(rgb, pixels.view[solid], metered_log_gains(metered))
    est = estimate_light(pts.position, pts.normal, pts.geometric_normal, rgb, geometry,
                         generator=torch.Generator().manual_seed(cfg.seed), ray_offset=cfg.ray_offset,
                         seen_sun=seen_sun)
    init = sg_from_light(est, cfg.light.num_lobes, sharp=cfg.light.sharpness_init_peak)
    set_sg_parameters(model.env, init)
    return init


FAR = 100.0
"""a geometry more than this many of its diagonals from every camera is suspicious (other units, another
world)"""


def check_in_view(scene: SceneData, box: tuple[Tensor, Tensor], source: GeometrySource) -> None:
    """Warn when the geometry lies far from every camera (it is likely in another world or other units)."""
    lo, hi = (b.double() for b in box)
    diagonal = float((hi - lo).norm())
    nearest = float((scene.cameras.c2w[:, :3, 3].double() - 0.5 * (lo + hi)).norm(dim=-1).min())
    if nearest > FAR * max(diagonal, 1e-12):
        warnings.warn(f"{source.mesh}: the mesh (diagonal {diagonal:.3g}) is {nearest:.3g} from the nearest camera, "
                      f"over {FAR:g} diagonals: is it in the cameras' world and units?", stacklevel=2)


def prepare_fit(cfg: FitConfig, data: Path, *, mesh: Path | None = None, geometry_dir: Path | None = None,
                device: torch.device = torch.device("cpu"), dist: DistContext = DistContext(),
                checkpoint: LoadedCheckpoint | None = None,
                resume_of: tuple[Path, DataFingerprint] | None = None, say: Callable[[str], None] = lambda s: None,
                reconstruct: Callable[[], Path] | None = None) -> FitSession:
    """The fit of ``data`` (any format nefii reads) on ``mesh``, ``geometry_dir`` (the output of ``nefii
    geometry``) or the dataset's own mesh, ready to train: first hits cast, model built, light initialised,
    or, with ``checkpoint`` (:func:`nefii.io.checkpoints.load_latest_checkpoint`), the training state in it. ``resume_of`` (the run folder and the data in its manifest) refuses
    data other than that before anything is trained. ``say`` gets one line per stage. ``reconstruct``, where
    none of the three exists, makes a ``nefii geometry`` folder from the images and returns it."""
    scene = load_scene(data, "train")
    scene, line = training_images(scene, cfg.max_image_side)
    if line:
        say(line)
    if mesh is None and geometry_dir is None and scene.mesh_path is None and reconstruct is not None:
        geometry_dir = reconstruct()
    source = resolve_source(mesh, geometry_dir, scene.mesh_path, cfg.geometry_mode, data)
    cfg, source = adapt_to_source(cfg, source)
    geometry, features = source.open()
    data_print = fingerprint(scene, source.mesh)
    if resume_of is not None:
        require_same(resume_of[1], data_print, resume_of[0])
    box = tuple(torch.from_numpy(b.copy()) for b in geometry.bounds)
    say(f"{len(scene)} views {scene.width}x{scene.height} from {scene.root} ({scene.format}); "
        f"{describe_geometry(source, geometry, cfg, features.dim if features else 0)}")
    check_in_view(scene, box, source)
    check_alignment(scene, geometry, source.mesh)
    pixels = first_hits(scene, geometry).to(device)
    check_winding(pixels.points, source)
    seen_background = len(pixels.bg_dirs)
    pixels, backdrop = without_backdrop(pixels)
    clipped = 0 if scene.clipped is None else int(scene.clipped.sum())
    unit = radiance_unit(pixels.rgb[pixels.solid], scene.root)
    if unit != 1.0:                     # no copy of every colour where the images are taken as they are
        pixels = pixels.scaled(1.0 / unit)
    edges = int(pixels.edge.sum())
    say(f"{len(pixels.points)} object pixels" + (f" ({edges} on the silhouette, fitted as object and sky mixed)"
                                                  if edges else "") + f", {len(pixels.bg_dirs)} background pixels"
        + (f"; {clipped} clipped pixels (some channel at the file's top value) left out" if clipped else ""))
    if backdrop is not None:
        say(f"the {seen_background} background pixels are one colour ({', '.join(f'{c:.3g}' for c in backdrop.tolist())}):"
            " a backdrop composited behind the object, not the environment; left out of the light's fit")
    if unit != 1.0:
        say(f"the images are {'brighter' if unit > 1.0 else 'darker'} than the fit is made for: fitted in units of "
            f"{unit:.4g} of their radiance (the written light and cache are in theirs)")
    if scene.exposure is not None:
        span = float(scene.exposure.log2().max() - scene.exposure.log2().min())
        if cfg.exposure == "per_view":
            say(f"per-view gains start from the photos' EXIF exposures ({span:.1f} stops apart)")
        elif span > 1.0 / 3.0:
            say(f"the photos' EXIF exposures are {span:.1f} stops apart: --set exposure=per_view learns a gain "
                "per photo")
    model = build_model(cfg, box, features)
    sun_lobe = None
    if checkpoint is None and shading_start(cfg):      # the sky's clipping is read only for the start that uses it
        bg = None if backdrop is not None else background_clipping(scene, geometry)
        seen_sun = None if bg is None else sky_sun(*bg)
        init = initialise_light(model, pixels, geometry, cfg, scene.exposure, seen_sun)
        sun_lobe = init.sun_lobe
        n_sharp = int((init.sharpness == cfg.light.sharpness_init_peak).sum())
        if n_sharp:
            say(f"lighting initialised from shading and shadows ({n_sharp} sharp lobes)")
        elif sun_lobe is not None and seen_sun is not None:
            say("lighting initialised from shading and shadows (no sharp peak: a lobe on the light source the "
                "background's clipped pixels see, sharpened when the roughness warm-up ends)")
        elif sun_lobe is not None:
            say("lighting initialised from shading and shadows (no sharp peak: a lobe on the direction that best "
                "explains the shading, sharpened when the roughness warm-up ends)")
    trainer = Trainer(cfg, model, geometry, pixels, device, dist, num_views=len(scene), metered=scene.exposure,
                      sun_lobe=sun_lobe, radiance_unit=unit)
    if checkpoint is not None:
        checkpoint.restore(trainer.load_state_dict, "this run's model")
        say(f"resumed from {checkpoint.path} at step {trainer.step}")
    return FitSession(cfg, scene, source, geometry, box, pixels, trainer, unit, data_print)
