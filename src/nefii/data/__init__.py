"""Dataset readers: every format becomes one typed :class:`SceneData` (contract: ``design.md`` here).

    scene = load_scene("path/to/scene", split="train")   # format detected from the files present
    scene.images, scene.masks, scene.cameras.K, scene.cameras.c2w   # linear RGB, bool, OpenCV c2w
"""
from .load import FORMATS, Format, detect_format, load_scene
from .scene import Cameras, GroundTruth, Relit, SceneData

__all__ = ["Cameras", "FORMATS", "Format", "GroundTruth", "Relit", "SceneData", "detect_format", "load_scene"]
