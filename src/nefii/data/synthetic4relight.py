"""The Synthetic4Relight layout (InvRender, Zhang et al. CVPR 2022), as InvRender's ``SynDataset`` reads it.

    transforms_{split}.json        camera_angle_x; frames: file_path (``train/0``), transform_matrix
    train/K_rgb.exr, K_mask.png    linear radiance and mask (training)
    test/K_rgba.png                sRGB image, alpha = mask (testing)
    test/K_albedo.png, K_rough.png ground truth (albedo sRGB-encoded, roughness stored linearly)
    test_rli/envmap{6,12}_K.png    optional: test views under two other lights

``transform_matrix`` is camera-to-world in **OpenCV** axes here (unlike NeRF-synthetic):
InvRender uses it unchanged with IDR's pinhole lift (x right, y down, z forward). As in
InvRender, translations are halved so that the object fits the unit sphere;
``scene_to_source = diag(2, 2, 2, 1)`` undoes it. ``fx = fy = W / (2 tan(camera_angle_x / 2))``,
principal point at the image centre. The dataset's environment maps live outside the scene
folder (InvRender's ``code/envmaps``) in another orientation convention and are not read.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from ..errors import InputError
from .files import matrix, read_data_map, read_json
from .nerf import frames_of, intrinsics
from .scene import GroundTruth, Relit, SceneData
from .validate import check_c2w, check_size
from .assemble import View, frame_indices, make_scene, read_colour_stack, read_views

NAME = "synthetic4relight"
DESCRIPTION = "transforms_{split}.json with {split}/K_rgb.exr + K_mask.png or K_rgba.png (Synthetic4Relight)"

TRANSLATION_SCALE = 0.5
"""InvRender's ``poses[..., 3] /= 2``"""

IMAGE_SUFFIX = {"train": "_rgb.exr", "test": "_rgba.png"}


def _image_suffix(split: str) -> str:
    return IMAGE_SUFFIX.get(split, "_rgb.exr")


def detect(root: Path, split: str) -> bool:
    path = root / f"transforms_{split}.json"
    if not path.is_file():
        return False
    frames = frames_of(read_json(path), path)
    fp = frames[0]["file_path"]
    return any((root / (fp + s)).is_file() for s in IMAGE_SUFFIX.values())


def _relit(root: Path, stems: list[str], size: tuple[int, int]) -> list[Relit]:
    folder = root / "test_rli"
    if not folder.is_dir():
        return []
    names = sorted({p.name.split("_")[0] for p in folder.glob("*_*.png")})
    out = []
    for env in names:
        images = read_colour_stack([folder / f"{env}_{s}.png" for s in stems], size)
        out.append(Relit(name=env, images=images, envmap=None))
    return out


def read(root: Path, split: str) -> SceneData:
    path = root / f"transforms_{split}.json"
    meta = read_json(path)
    frames = frames_of(meta, path)
    suffix = _image_suffix(split)
    views, poses = [], []
    for i, f in enumerate(frames):
        where = f"frame {i} ({f['file_path']})"
        c2w = check_c2w(matrix(f["transform_matrix"], ((4, 4), (3, 4)), path, where), path, where)
        c2w[:3, 3] *= TRANSLATION_SCALE
        poses.append(c2w)
        image = root / (f["file_path"] + suffix)
        if not image.is_file():
            raise InputError(image, "image file not found")
        mask = root / (f["file_path"] + "_mask.png")
        views.append(View(image=image, mask=mask if mask.is_file() else None))
    stack = read_views(views)
    h, w = stack.images.shape[1:3]
    Ks = [intrinsics(meta, f, w, h, path, f"frame {i} ({f['file_path']})") for i, f in enumerate(frames)]

    stems = [Path(f["file_path"]).name for f in frames]
    gt: dict[str, torch.Tensor] = {}
    for kind, key, channels, srgb in (("albedo", "_albedo.png", 3, True), ("roughness", "_rough.png", 1, False)):
        files = [root / (f["file_path"] + key) for f in frames]
        present = [p.is_file() for p in files]
        if not any(present):
            continue
        if not all(present):
            raise InputError(files[present.index(False)], f"ground-truth {kind} map missing (other views have one)")
        arrs = [read_data_map(p, channels, srgb=srgb) for p in files]
        for p, a in zip(files, arrs):
            check_size(a.shape, p, (h, w), views[0].image)
        stacked = np.stack(arrs)
        gt[kind] = torch.from_numpy(stacked[..., 0] if channels == 1 else stacked)
    if gt and stack.masks is not None:
        gt["mask"] = torch.from_numpy(stack.masks)

    return make_scene(
        root=root, split=split, fmt=NAME, views=views, stack=stack, K=Ks, c2w=poses,
        indices=frame_indices(stems),
        scene_to_source=np.diag([1 / TRANSLATION_SCALE] * 3 + [1.0]),
        ground_truth=GroundTruth(**gt) if gt else None,
        relit=_relit(root, stems, (h, w)) if split == "test" else (),
    )
