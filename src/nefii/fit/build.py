"""Build the model's fields from a config (one place that knows the presets' network shapes)."""
from __future__ import annotations

import torch
from torch import Tensor

from ..fields.cache import RadianceCache
from ..fields.encodings import FourierFeatures, HashGrid
from ..fields.environment import EnvmapEnvironment, SGEnvironment
from ..fields.features import FeatureField
from ..fields.material import MaterialField
from .config import EncodingConfig, FitConfig
from .model import NeFIIModel


def make_encoding(cfg: EncodingConfig) -> HashGrid | FourierFeatures:
    if cfg.kind == "hashgrid":
        return HashGrid(cfg.levels, cfg.features_per_level, cfg.log2_table_size, cfg.base_resolution,
                        cfg.max_resolution)
    if cfg.kind == "fourier":
        return FourierFeatures(3, cfg.fourier_freqs)
    raise ValueError(f"unknown encoding kind {cfg.kind!r} (hashgrid | fourier)")


def build_model(cfg: FitConfig, box: tuple[Tensor, Tensor], features: FeatureField | None = None) -> NeFIIModel:
    """Fields over the scene box (padded by 5% so that points on the box faces stay inside); with
    ``features`` (a frozen SDF's), the material and the cache take its feature vector as input too."""
    lo, hi = (torch.as_tensor(b, dtype=torch.float32) for b in box)
    pad = 0.05 * (hi - lo).max()
    offset = cfg.material_offset * float((hi - lo).norm())
    box, material_box = (lo - pad, hi + pad), (lo - pad - offset, hi + pad + offset)
    torch.manual_seed(cfg.seed)
    material = MaterialField(make_encoding(cfg.material.encoding), cfg.material.hidden, cfg.material.layers,
                             material_box, features, normal_offset=offset,
                             brdf=cfg.brdf)
    cache = RadianceCache(make_encoding(cfg.cache.encoding), cfg.cache_dir_freqs, cfg.cache.hidden,
                          cfg.cache.layers, box, features)
    if cfg.light.kind == "sg":
        env = SGEnvironment(cfg.light.num_lobes, cfg.light.sharpness_min, cfg.light.sharpness_max,
                            cfg.light.init_radiance, seed=cfg.seed)
    elif cfg.light.kind == "envmap":
        env = EnvmapEnvironment(cfg.light.envmap_height, 2 * cfg.light.envmap_height, cfg.light.init_radiance)
    else:
        raise ValueError(f"unknown light kind {cfg.light.kind!r} (sg | envmap)")
    return NeFIIModel(material, cache, env)
