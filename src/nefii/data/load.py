"""``load_scene``: find which dataset format a folder holds and read one split of it."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

from ..errors import InputError
from . import colmap, nerf, nerfstudio, neus, physg, stanford_orb, synthetic4relight, tensoir
from .scene import SceneData

SPLITS = ("train", "test")


@dataclass(frozen=True)
class Format:
    """A dataset layout nefii reads."""

    name: str
    """what ``SceneData.format`` and ``load_scene(format=...)`` call it"""
    description: str
    """the files that identify it, for messages (``{split}`` is filled in)"""
    detect: Callable[[Path, str], bool]
    """whether a folder holds this format for a split"""
    read: Callable[..., SceneData]
    """``read(folder, split, **options)``"""
    has_splits: bool
    """whether one folder holds both splits (``transforms_{split}.json``); if not, a split lives in
    its own subfolder ``<root>/<split>/``, or the folder itself is the training split"""


FORMATS: dict[str, Format] = {f.name: f for f in (
    # Synthetic4Relight before nerf: both have transforms_{split}.json, only it has K_rgb.exr etc.
    Format(synthetic4relight.NAME, synthetic4relight.DESCRIPTION, synthetic4relight.detect,
           synthetic4relight.read, True),
    # Stanford-ORB before nerf: both have transforms_{split}.json, only it has {split}_mask/
    Format(stanford_orb.NAME, stanford_orb.DESCRIPTION, stanford_orb.detect, stanford_orb.read, True),
    Format(nerf.NAME, nerf.DESCRIPTION, nerf.detect, nerf.read, True),
    Format(tensoir.NAME, tensoir.DESCRIPTION, tensoir.detect, tensoir.read, True),
    # nerfstudio after nerf: a folder with transforms_{split}.json is read by it even beside a transforms.json
    Format(nerfstudio.NAME, nerfstudio.DESCRIPTION, nerfstudio.detect, nerfstudio.read, True),
    Format(neus.NAME, neus.DESCRIPTION, neus.detect, neus.read, False),
    Format(physg.NAME, physg.DESCRIPTION, physg.detect, physg.read, False),
    Format(colmap.NAME, colmap.DESCRIPTION, colmap.detect, colmap.read, False),
)}
"""the readers, in the order ``load_scene`` tries them"""


def _folder_for(fmt: Format, root: Path, split: str) -> Path | None:
    """Where ``fmt`` holds ``split`` under ``root``, or ``None``."""
    if fmt.has_splits:
        return root if fmt.detect(root, split) else None
    sub = root / split
    if sub.is_dir() and fmt.detect(sub, split):
        return sub
    if split == "train" and fmt.detect(root, split):
        return root
    return None


def detect_format(root: str | Path, split: str = "train") -> tuple[Format, Path]:
    """The format of ``root`` for ``split`` and the folder to read; :class:`InputError` if none matches."""
    root = Path(root)
    if split not in SPLITS:
        raise InputError(None, f"unknown split '{split}' (expected one of {', '.join(SPLITS)})")
    if not root.is_dir():
        raise InputError(root, "not a folder" if root.exists() else "folder not found")
    for fmt in FORMATS.values():
        folder = _folder_for(fmt, root, split)
        if folder is not None:
            return fmt, folder
    looked = "; ".join(f"{f.description.format(split=split)}" + ("" if f.has_splits else f" here or in {split}/")
                       for f in FORMATS.values())
    raise InputError(root, f"no dataset found for split '{split}'; looked for: {looked}")


def load_scene(path: str | Path, split: str = "train", *, format: str | None = None, **options: Any) -> SceneData:
    """Read one split of the scene at ``path`` into :class:`SceneData`.

    ``format`` names a reader (a key of :data:`FORMATS`) instead of detecting it. ``options`` go
    to the reader: ``prefer`` (nerf, stanford_orb: suffix order for images).
    Every problem with the files is an :class:`InputError` naming the file.
    """
    root = Path(path)
    if format is None:
        fmt, folder = detect_format(root, split)
    else:
        if format not in FORMATS:
            raise InputError(None, f"unknown dataset format '{format}' (known: {', '.join(FORMATS)})")
        fmt = FORMATS[format]
        folder = _folder_for(fmt, root, split) if root.is_dir() else None
        if folder is None:
            raise InputError(root, f"not a {fmt.name} dataset for split '{split}' "
                                   f"(expected {fmt.description.format(split=split)})")
    return fmt.read(folder, split, **options)
