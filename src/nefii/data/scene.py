"""The one typed scene every dataset reader returns (contract: ``design.md`` beside this file).

Shapes: ``N`` views of ``H x W`` pixels; ``He x We`` an environment map.
All tensors start on the CPU; :meth:`SceneData.to` moves every one of them (dtypes kept).
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

import torch
from jaxtyping import Bool, Float
from torch import Tensor

T = TypeVar("T")


def _to(obj: T, device: torch.device | str) -> T:
    """A copy of the dataclass ``obj`` with every tensor field (and nested bundle) on ``device``."""
    def move(v: Any) -> Any:
        if isinstance(v, Tensor):
            return v.to(device)
        if dataclasses.is_dataclass(v) and not isinstance(v, type):
            return _to(v, device)
        if isinstance(v, tuple):
            return tuple(move(x) for x in v)
        return v
    return dataclasses.replace(obj, **{f.name: move(getattr(obj, f.name)) for f in dataclasses.fields(obj)})


def _expect(cond: bool, what: str) -> None:
    if not cond:
        raise ValueError(what)


@dataclass(frozen=True)
class Cameras:
    """Pinhole cameras in nefii's convention (OpenCV axes: x right, y down, z forward)."""

    K: Float[Tensor, "N 3 3"]
    """intrinsics in pixels, float64; pixel ``(i, j)`` has its centre at ``(j + 0.5, i + 0.5)``"""
    c2w: Float[Tensor, "N 4 4"]
    """camera-to-world, float64, rotation block orthonormal with determinant +1"""
    height: int
    """image height H in pixels (all views share it)"""
    width: int
    """image width W in pixels"""

    def __post_init__(self) -> None:
        n = self.K.shape[0]
        _expect(self.K.shape == (n, 3, 3), f"Cameras.K must be (N, 3, 3), got {tuple(self.K.shape)}")
        _expect(self.c2w.shape == (n, 4, 4), f"Cameras.c2w must be ({n}, 4, 4), got {tuple(self.c2w.shape)}")

    def __len__(self) -> int:
        return self.K.shape[0]

    def to(self, device: torch.device | str) -> "Cameras":
        return _to(self, device)


@dataclass(frozen=True)
class GroundTruth:
    """Per-view ground-truth maps of a synthetic scene (usually its test split); any may be absent.

    Colours and radiance are linear; a map is ``None`` when the dataset has no file of that kind.
    """

    albedo: Float[Tensor, "N H W 3"] | None = None
    """diffuse base colour"""
    roughness: Float[Tensor, "N H W"] | None = None
    """perceptual roughness in [0, 1] (GGX alpha = roughness^2)"""
    specular: Float[Tensor, "N H W 3"] | None = None
    """radiance reflected by the specular lobe at the first hit"""
    diffuse: Float[Tensor, "N H W 3"] | None = None
    """radiance reflected by the diffuse lobe at the first hit"""
    normal: Float[Tensor, "N H W 3"] | None = None
    """world-space shading normal"""
    depth: Float[Tensor, "N H W"] | None = None
    """depth as the renderer wrote it (nefii synth: z-depth from the camera centre, see docs/datasets.md)"""
    mask: Bool[Tensor, "N H W"] | None = None
    """object coverage"""

    def kinds(self) -> tuple[str, ...]:
        """Names of the maps present."""
        return tuple(f.name for f in dataclasses.fields(self) if getattr(self, f.name) is not None)

    def to(self, device: torch.device | str) -> "GroundTruth":
        return _to(self, device)


@dataclass(frozen=True)
class Relit:
    """Views of the object under another, known environment. Two kinds:

    * the split's own views relit (nefii layout ``relight/<name>/``): ``images`` only, one ``envmap``;
      ``cameras``, ``masks``, ``indices`` and ``view_envmaps`` are ``None``;
    * other photographs at their own poses, each under its own measured map (Stanford-ORB
      ``transforms_novel.json``): ``cameras`` and ``indices`` set (``masks`` where the dataset has them),
      one map per view in ``view_envmaps``, ``envmap`` ``None``.
    """

    name: str
    """the environment's name: the folder under ``relight/`` (nefii), the capture scene (Stanford-ORB)"""
    images: Float[Tensor, "N H W 3"]
    """linear straight colour"""
    envmap: Float[Tensor, "He We 3"] | None
    """the one environment of every view, equirectangular in nefii's mapping (``nefii.render.equirect``);
    ``None`` when the dataset has no file for it or each view has its own (``view_envmaps``)"""
    view_envmaps: Float[Tensor, "N He We 3"] | None = None
    """each view's own environment, in the world frame and nefii's mapping (Stanford-ORB: the light probe
    taken with each photograph)"""
    cameras: Cameras | None = None
    """these views' own cameras; ``None``: the split's"""
    masks: Bool[Tensor, "N H W"] | None = None
    """these views' object masks; ``None``: the split's (only with the split's own cameras), or none"""
    indices: tuple[int, ...] | None = None
    """these views' frame indices (outputs are named by them); ``None``: the split's"""

    def __post_init__(self) -> None:
        n = self.images.shape[0]
        _expect(self.images.ndim == 4 and self.images.shape[-1] == 3,
                f"relit '{self.name}' images must be (N, H, W, 3), got {tuple(self.images.shape)}")
        if self.cameras is None:
            _expect(self.masks is None and self.indices is None,
                    f"relit '{self.name}': masks and indices come with the views' own cameras")
        else:
            h, w = self.images.shape[1:3]
            _expect(len(self.cameras) == n and (self.cameras.height, self.cameras.width) == (h, w),
                    f"relit '{self.name}': {len(self.cameras)} cameras of {self.cameras.width}x"
                    f"{self.cameras.height} for {n} images of {w}x{h}")
            _expect(self.indices is not None and len(self.indices) == n,
                    f"relit '{self.name}': its own cameras need one index per view")
            if self.masks is not None:
                _expect(self.masks.shape == (n, h, w) and self.masks.dtype == torch.bool,
                        f"relit '{self.name}' masks must be bool ({n}, {h}, {w}), got {self.masks.dtype} "
                        f"{tuple(self.masks.shape)}")
        if self.view_envmaps is not None:
            _expect(self.view_envmaps.ndim == 4 and self.view_envmaps.shape[0] == n
                    and self.view_envmaps.shape[-1] == 3,
                    f"relit '{self.name}' view_envmaps must be ({n}, He, We, 3), got {tuple(self.view_envmaps.shape)}")

    def __len__(self) -> int:
        return self.images.shape[0]

    def environment(self, v: int) -> Float[Tensor, "He We 3"] | None:
        """The map that lights view ``v``: its own, else the shared one (``None`` if neither)."""
        return self.view_envmaps[v] if self.view_envmaps is not None else self.envmap

    def to(self, device: torch.device | str) -> "Relit":
        return _to(self, device)


@dataclass(frozen=True)
class SceneData:
    """One split of one scene, whatever format it was read from."""

    images: Float[Tensor, "N H W 3"]
    """linear float32 straight (not premultiplied) colour"""
    masks: Bool[Tensor, "N H W"] | None
    """object masks; ``None`` when the dataset has neither mask files nor alpha"""
    cameras: Cameras
    """intrinsics and OpenCV camera-to-world poses"""
    names: tuple[str, ...]
    """each view's image file, relative to ``root`` (POSIX separators)"""
    indices: tuple[int, ...]
    """each view's frame index: the ``K`` of ``r_K`` (outputs are named by it), else its position"""
    split: str
    """``"train"`` or ``"test"``"""
    format: str
    """the reader that produced it (a key of ``nefii.data.FORMATS``)"""
    root: Path
    """the folder the data was read from"""
    scene_to_source: Float[Tensor, "4 4"]
    """float64 similarity taking this scene's world coordinates to the dataset's own
    (identity unless the reader normalised, e.g. NeuS ``scale_mat``, Synthetic4Relight's x2)"""
    ground_truth: GroundTruth | None = None
    """ground-truth maps per view, when the dataset has some"""
    mesh_path: Path | None = None
    """ground-truth geometry in this scene's world coordinates (nefii layout ``mesh.ply``)"""
    envmap: Float[Tensor, "He We 3"] | None = None
    """the lighting of ``images``, equirectangular in nefii's mapping, linear"""
    relit: tuple[Relit, ...] = ()
    """views under other, known environments (test split): these views relit (nefii layout), or other
    photographs at their own poses (Stanford-ORB); see :class:`Relit`"""
    background_visible: bool = True
    """whether non-object pixels show the environment (photos, or renders with the sky); ``False`` when
    the background is transparent (masks from alpha, e.g. RGBA renders): those pixels observe nothing"""
    clipped: Bool[Tensor, "N H W"] | None = None
    """pixels saturated in some channel of an 8/16-bit file (the scene was at least that bright): left out of
    the fit's photometric loss; ``None`` when no pixel is"""
    exposure: Float[Tensor, "N"] | None = None
    """each photo's exposure from its EXIF (``t * ISO / N^2``, float64), when every view has one: where the
    fit's per-view gains start; ``None`` otherwise"""

    def __post_init__(self) -> None:
        imgs = self.images
        _expect(imgs.ndim == 4 and imgs.shape[-1] == 3,
                f"SceneData.images must be (N, H, W, 3), got {tuple(imgs.shape)}")
        n, h, w = imgs.shape[:3]
        _expect(imgs.dtype == torch.float32, f"SceneData.images must be float32, got {imgs.dtype}")
        _expect((self.cameras.height, self.cameras.width) == (h, w),
                f"cameras are {self.cameras.width}x{self.cameras.height} but images {w}x{h}")
        _expect(len(self.cameras) == n, f"{len(self.cameras)} cameras for {n} images")
        _expect(len(self.names) == n and len(self.indices) == n,
                f"{len(self.names)} names and {len(self.indices)} indices for {n} images")
        if self.masks is not None:
            _expect(self.masks.shape == (n, h, w) and self.masks.dtype == torch.bool,
                    f"SceneData.masks must be bool ({n}, {h}, {w}), got {self.masks.dtype} {tuple(self.masks.shape)}")
        if self.clipped is not None:
            _expect(self.clipped.shape == (n, h, w) and self.clipped.dtype == torch.bool,
                    f"SceneData.clipped must be bool ({n}, {h}, {w}), got {self.clipped.dtype} {tuple(self.clipped.shape)}")
        if self.exposure is not None:
            _expect(self.exposure.shape == (n,), f"SceneData.exposure must be ({n},), got {tuple(self.exposure.shape)}")
        _expect(self.scene_to_source.shape == (4, 4), "SceneData.scene_to_source must be 4x4")
        if self.ground_truth is not None:
            for kind in self.ground_truth.kinds():
                shape = getattr(self.ground_truth, kind).shape
                _expect(tuple(shape[:3]) == (n, h, w),
                        f"ground truth {kind} has shape {tuple(shape)}, views are ({n}, {h}, {w})")
        for r in self.relit:
            _expect(r.cameras is not None or r.images.shape == imgs.shape,
                    f"relit '{r.name}' images {tuple(r.images.shape)} != {tuple(imgs.shape)}")

    def __len__(self) -> int:
        return self.images.shape[0]

    @property
    def height(self) -> int:
        return self.cameras.height

    @property
    def width(self) -> int:
        return self.cameras.width

    def source_c2w(self) -> Float[Tensor, "N 4 4"]:
        """Camera-to-world matrices in the dataset's own world frame (undoing any normalisation).

        ``scene_to_source = [s Q | c]`` (a similarity: scale ``s``, rotation ``Q``) moves camera
        centres to ``s Q t + c`` and turns rotations by ``Q``.
        """
        S = self.scene_to_source.to(self.cameras.c2w)
        A = S[:3, :3]
        Q = A / torch.linalg.det(A).abs().pow(1.0 / 3.0)
        out = self.cameras.c2w.clone()
        out[:, :3, :3] = Q @ out[:, :3, :3]
        out[:, :3, 3] = out[:, :3, 3] @ A.T + S[:3, 3]
        return out

    def to(self, device: torch.device | str) -> "SceneData":
        """A copy with every tensor on ``device`` (dtypes kept: images float32, cameras float64)."""
        return _to(self, device)
