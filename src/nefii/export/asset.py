"""The exported asset: a Y-up GLB (or OBJ/MTL + PNGs), the environment map and a README.

glTF is Y-up, nefii's world is Z-up (docs/design.md). The writers store world ``(x, y, z)`` as
``(x, z, -y)``: the rotation of +90 degrees about +X that Blender's glTF exporter applies, so
Blender's importers (glTF, and OBJ with its default Forward -Z / Up Y) turn it back and the
object lands upright in the fitted scene's coordinates and units.

Material, glTF 2.0 PBR metallic-roughness:

    baseColorTexture          diffuse albedo, sRGB, 8-bit PNG
    metallicRoughnessTexture  R = 255 (unused by glTF; "no occlusion" for tools that read ORM),
                              G = roughness (linear; perceptual, GGX alpha = roughness^2), B = metallic = 0
    metallicFactor 0, roughnessFactor 1, baseColorFactor 1; the glTF default dielectric
    (IOR 1.5, F0 = 0.04) is the BRDF the fit assumed.
"""
from __future__ import annotations

import io
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import torch
from jaxtyping import Float
from PIL import Image

from ..fit.model import NeFIIModel
from ..io.atomic import write_bytes_atomic, write_text_atomic
from ..io.exr import write_exr
from ..io.images import linear_to_srgb, to_uint8
from .bake import BakedTextures, bake_textures
from .unwrap import UVAtlas, unwrap

Z_UP_TO_Y_UP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])
"""world (x, y, z), +Z up  ->  file (x, z, -y), +Y up"""
ENVMAP_EXPORT_SIZE = (512, 1024)
MATERIAL_NAME = "nefii"


@dataclass(frozen=True)
class BakedAsset:
    atlas: UVAtlas
    positions: Float[np.ndarray, "V 3"]
    """atlas vertices in world space (+Z up)"""
    normals: Float[np.ndarray, "V 3"]
    """unit vertex normals in world space, shared across UV seams"""
    textures: BakedTextures


def bake_asset(model: NeFIIModel, vertices: np.ndarray, faces: np.ndarray, normals: np.ndarray, size: int,
               progress: Callable[[int, int], None] | None = None,
               lookup_normals: np.ndarray | None = None) -> BakedAsset:
    """UV-unwrap the mesh into a ``size``-square atlas and bake ``model``'s material over it. ``normals`` are
    the asset's (shading) vertex normals, ``lookup_normals`` the material lookup's (default: ``normals``)."""
    atlas = unwrap(vertices, faces, size)
    positions = np.asarray(vertices, dtype=np.float64)[atlas.source]
    atlas_normals = np.asarray(normals, np.float32)[atlas.source]
    lookup = atlas_normals if lookup_normals is None else np.asarray(lookup_normals, np.float32)[atlas.source]
    textures = bake_textures(model, positions, lookup, atlas, progress)
    return BakedAsset(atlas, positions.astype(np.float32), atlas_normals, textures)


# ---------------------------------------------------------------- textures
def base_color_image(t: BakedTextures) -> Image.Image:
    return Image.fromarray(to_uint8(linear_to_srgb(t.albedo)), "RGB")


def metallic_roughness_image(t: BakedTextures) -> Image.Image:
    g = to_uint8(t.roughness)
    return Image.fromarray(np.stack([np.full_like(g, 255), g, np.zeros_like(g)], -1), "RGB")


def roughness_image(t: BakedTextures) -> Image.Image:
    return Image.fromarray(to_uint8(t.roughness), "L")


def _y_up(a: np.ndarray) -> np.ndarray:
    return (np.asarray(a, dtype=np.float64) @ Z_UP_TO_Y_UP.T).astype(np.float32)


# ---------------------------------------------------------------- glTF
def glb_bytes(asset: BakedAsset) -> bytes:
    """The asset as one binary glTF (trimesh's writer), Y-up."""
    import trimesh
    from trimesh.visual.material import PBRMaterial
    from trimesh.visual.texture import TextureVisuals

    material = PBRMaterial(name=MATERIAL_NAME, baseColorTexture=base_color_image(asset.textures),
                           metallicRoughnessTexture=metallic_roughness_image(asset.textures),
                           baseColorFactor=[1.0, 1.0, 1.0, 1.0], metallicFactor=0.0, roughnessFactor=1.0)
    uv_gl = asset.atlas.uv * np.array([1.0, -1.0]) + np.array([0.0, 1.0])   # trimesh keeps OpenGL's v-up
    mesh = trimesh.Trimesh(vertices=_y_up(asset.positions), faces=asset.atlas.faces,
                           vertex_normals=_y_up(asset.normals), process=False,
                           visual=TextureVisuals(uv=uv_gl, material=material))
    return trimesh.exchange.gltf.export_glb(trimesh.Scene({MATERIAL_NAME: mesh}), include_normals=True)


def write_glb(path: Path, asset: BakedAsset) -> list[Path]:
    write_bytes_atomic(path, glb_bytes(asset))
    return [path]


# ---------------------------------------------------------------- OBJ
def write_obj(path: Path, asset: BakedAsset) -> list[Path]:
    """``NAME.obj`` (Y-up) + ``NAME.mtl`` + ``NAME_albedo.png`` (sRGB) + ``NAME_roughness.png`` (linear).

    The MTL uses the PBR extension (``Pr``/``map_Pr`` roughness, ``Pm`` metallic) that Blender's
    OBJ importer reads; the textures and the MTL are written before the OBJ that names them.
    """
    stem = path.stem
    albedo, rough, mtl = (path.with_name(f"{stem}_albedo.png"), path.with_name(f"{stem}_roughness.png"),
                          path.with_suffix(".mtl"))
    for img, dst in ((base_color_image(asset.textures), albedo), (roughness_image(asset.textures), rough)):
        buf = io.BytesIO()
        img.save(buf, format="PNG")
        write_bytes_atomic(dst, buf.getvalue())
    write_text_atomic(mtl, "\n".join([
        "# nefii export: diffuse albedo (sRGB) and roughness (linear), metallic 0", f"newmtl {MATERIAL_NAME}",
        "Kd 1.000000 1.000000 1.000000", "Ks 0.000000 0.000000 0.000000", "Pr 1.000000", "Pm 0.000000",
        "illum 2", f"map_Kd {albedo.name}", f"map_Pr {rough.name}", ""]))
    v, n = _y_up(asset.positions), _y_up(asset.normals)
    vt = asset.atlas.uv * np.array([1.0, -1.0]) + np.array([0.0, 1.0])      # OBJ's v points up
    f = asset.atlas.faces + 1
    lines = ["# nefii export: Y-up (world x, y, z stored as x, z, -y); one v/vt/vn per index",
             f"mtllib {mtl.name}", "o nefii"]
    lines += [f"v {a:.7g} {b:.7g} {c:.7g}" for a, b, c in v]
    lines += [f"vt {a:.7g} {b:.7g}" for a, b in vt]
    lines += [f"vn {a:.6g} {b:.6g} {c:.6g}" for a, b, c in n]
    lines += [f"usemtl {MATERIAL_NAME}", "s 1"]
    lines += [f"f {a}/{a}/{a} {b}/{b}/{b} {c}/{c}/{c}" for a, b, c in f]
    write_text_atomic(path, "\n".join(lines) + "\n")
    return [albedo, rough, mtl, path]


# ---------------------------------------------------------------- light and README
@torch.no_grad()
def environment_image(model: NeFIIModel, size: tuple[int, int] = ENVMAP_EXPORT_SIZE) -> np.ndarray:
    """The recovered environment, ``(H, W, 3)`` linear, in the docs/design.md (= Blender) mapping."""
    return model.env.to_equirect(*size).float().cpu().numpy()


def write_envmap(path: Path, model: NeFIIModel, size: tuple[int, int] = ENVMAP_EXPORT_SIZE) -> Path:
    write_exr(path, environment_image(model, size))
    return path


def readme_text(asset: Path, envmap: Path, fmt: str, run: Path, size: int) -> str:
    if fmt == "glb":
        files = f"  {asset.name:<22} the frozen mesh with the recovered material (glTF 2.0 binary, textures inside)"
        material = ("Material (glTF PBR metallic-roughness):\n"
                    f"  baseColorTexture          diffuse albedo, sRGB, {size}x{size}\n"
                    "  metallicRoughnessTexture  G = roughness (linear; GGX alpha = roughness^2), B = metallic = 0,\n"
                    "                            R = 255 (unused by glTF; 'no occlusion' to tools that read ORM)\n"
                    "  metallicFactor 0, roughnessFactor 1; specular is glTF's default dielectric (IOR 1.5,\n"
                    "  F0 = 0.04), the BRDF the fit assumed.\n")
        step1 = (f" 1. File > Import > glTF 2.0 (.glb/.gltf) and pick {asset.name}. The importer connects Base\n"
                 "    Color and, through a Separate Color node, the G channel (roughness) to the Principled BSDF.\n")
    else:
        stem = asset.stem
        files = (f"  {asset.name:<22} the frozen mesh (Wavefront OBJ, normals and UVs)\n"
                 f"  {stem + '.mtl':<22} its material: map_Kd = albedo, map_Pr = roughness, metallic 0\n"
                 f"  {stem + '_albedo.png':<22} diffuse albedo, sRGB, {size}x{size}\n"
                 f"  {stem + '_roughness.png':<22} roughness, linear grey (GGX alpha = roughness^2)")
        material = ""
        step1 = (f" 1. File > Import > Wavefront (.obj), pick {asset.name}, keep the default axes (Forward -Z,\n"
                 f"    Up Y). If Roughness is not connected, add an Image Texture with {stem}_roughness.png,\n"
                 "    set its Color Space to Non-Color and connect it to the Principled BSDF's Roughness.\n")
    return (f"nefii export of {run}\n\nFiles\n{files}\n"
            f"  {envmap.name:<22} the recovered environment light: equirectangular, linear float EXR\n"
            f"  {'README.txt':<22} this file\n\n"
            "Axes: the file is Y-up, as glTF requires: nefii's world (x, y, z), +Z up, is stored as\n"
            "(x, z, -y). Blender's importers turn Y-up back into Z-up, so the object lands upright, in\n"
            "the fitted scene's coordinates and units.\n\n"
            f"{material}\nIn Blender\n{step1}"
            " 2. World Properties > Surface > Color: Environment Texture, and open "
            f"{envmap.name}. Leave\n"
            "    its Vector input unconnected (no Mapping node, no rotation): nefii's equirectangular\n"
            "    mapping is Blender's default world mapping, so the light comes from where the fit found it.\n"
            " 3. Render with Cycles (the fit modelled light bouncing between parts of the object).\n\n"
            "Scale: inverse rendering recovers albedo and light up to one common factor; the albedo\n"
            "texture and this env map belong together (the per-channel albedo scale `nefii eval`\n"
            "reports against ground truth is not applied).\n")
