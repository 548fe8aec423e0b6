"""``nefii export RUN --out asset.glb``: the recovered material baked into textures on the frozen
mesh, as a Y-up glTF binary (or OBJ/MTL + PNGs), with the recovered light as ``envmap.exr`` and a
README on opening both in Blender, all beside ``--out``. It writes only those files, and replaces none
that exist (outside ``RUN/export``, its default folder) unless ``--force``."""
from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

from tqdm import tqdm

from ..errors import InputError
from ..export.asset import (ENVMAP_EXPORT_SIZE, BakedAsset, bake_asset, readme_text, write_envmap, write_glb,
                            write_obj)
from ..fit.model import NeFIIModel
from ..fit.outputs import load_run
from ..raycast import MeshGeometry
from ..io.atomic import write_text_atomic
from .common import pick_device, set_threads

FORMATS = ("glb", "obj")
TEXTURE_SIZES = (16, 8192)


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("export", help="bake the recovered material into a GLB/OBJ asset for Blender",
                       description=__doc__)
    p.add_argument("run", type=Path, help="run folder written by `nefii fit`")
    p.add_argument("--out", type=Path, default=None, help="asset file (default: RUN/export/asset.glb or .obj)")
    p.add_argument("--texture-size", default="2048", metavar="N",
                   help=f"side of the square textures in texels, {TEXTURE_SIZES[0]}..{TEXTURE_SIZES[1]} (default 2048)")
    p.add_argument("--format", choices=FORMATS, default=None,
                   help="glb (default; or taken from --out's suffix) or obj (OBJ/MTL + PNG textures)")
    p.add_argument("--force", action="store_true",
                   help="replace files of the same names beside --out (default: refuse)")
    p.add_argument("--device", default="auto", help="cpu | cuda | auto")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def texture_size(text: str) -> int:
    try:
        size = int(text)
    except ValueError:
        size = None
    if size is None or not TEXTURE_SIZES[0] <= size <= TEXTURE_SIZES[1]:
        raise InputError(None, f"--texture-size {text}: want a whole number of texels from "
                               f"{TEXTURE_SIZES[0]} to {TEXTURE_SIZES[1]}")
    return size


def output_path(out: Path | None, fmt: str | None, run_dir: Path) -> tuple[Path, str]:
    """The asset path and its format; refuses a suffix that contradicts --format, a folder, or a
    place that cannot be written, before anything is computed or written."""
    suffix = None if out is None else out.suffix.lower().lstrip(".")
    if fmt is None:
        fmt = suffix if suffix in FORMATS else "glb"
    if out is None:
        out = run_dir / "export" / f"asset.{fmt}"
    elif suffix != fmt:
        raise InputError(out, f"the file name should end in .{fmt} for --format {fmt}")
    check_writable(out)
    return out, fmt


def check_writable(out: Path) -> None:
    """``out`` can be created as a file: not a folder, under folders that exist or can be made."""
    if out.is_dir():
        raise InputError(out, "is a folder: give a file name")
    ancestor = out.parent
    while not ancestor.exists() and ancestor != ancestor.parent:
        ancestor = ancestor.parent
    if not ancestor.is_dir():
        raise InputError(out, f"cannot be written: {ancestor} is not a folder")
    if not os.access(ancestor, os.W_OK | os.X_OK):
        raise InputError(out, f"cannot be written: no permission to write in {ancestor}")


def files_written(out: Path, fmt: str) -> list[Path]:
    """Every file an export to ``out`` writes."""
    companions = [out.with_name(f"{out.stem}_albedo.png"), out.with_name(f"{out.stem}_roughness.png"),
                  out.with_suffix(".mtl")] if fmt == "obj" else []
    return [out, *companions, out.parent / "envmap.exr", out.parent / "README.txt"]


def check_no_overwrite(files: list[Path]) -> None:
    """Refuse to replace files that exist (the user's own, or another export's)."""
    existing = [p for p in files if p.exists()]
    if existing:
        more = f" (and {', '.join(p.name for p in existing[1:])})" if len(existing) > 1 else ""
        raise InputError(existing[0], f"exists{more}: export would replace it; pass --force to overwrite, or "
                                      "choose another --out")


def bake_with_progress(model: NeFIIModel, mesh: MeshGeometry, size: int, quiet: bool) -> BakedAsset:
    """``bake_asset`` with a progress bar over the texels decoded (it appears once their count is known)."""
    bars: list[tqdm] = []

    def progress(n: int, total: int) -> None:
        if not bars:
            bars.append(tqdm(total=total, desc="bake", unit="texel", unit_scale=True, disable=quiet))
        bars[0].update(n)

    try:
        return bake_asset(model, mesh.vertices, mesh.faces, mesh.vertex_normals, size, progress,
                          lookup_normals=mesh.lookup_normals)
    finally:
        for bar in bars:
            bar.close()


def run(args: argparse.Namespace) -> int:
    size = texture_size(args.texture_size)
    out, fmt = output_path(args.out, args.format, args.run)
    if args.out is not None and not args.force:       # RUN/export is the run's own
        check_no_overwrite(files_written(out, fmt))
    device = pick_device(args.device)
    fitted = load_run(args.run, device)
    set_threads(fitted.config.threads)
    mesh = fitted.geometry.open_mesh(threads=1)
    t0 = time.time()
    asset = bake_with_progress(fitted.model, mesh, size, args.quiet)
    envmap = write_envmap(out.parent / "envmap.exr", fitted.model)
    readme = out.parent / "README.txt"
    write_text_atomic(readme, readme_text(out, envmap, fmt, args.run, size))
    written = (write_glb if fmt == "glb" else write_obj)(out, asset)
    cover = asset.textures.covered.mean()
    print(f"nefii export: {len(asset.atlas.faces)} triangles, {size}x{size} textures "
          f"({100 * cover:.0f}% of texels decoded from the field), {time.time() - t0:.1f} s")
    for path in (*written, envmap, readme):
        print(f"  {path}")
    h, w = ENVMAP_EXPORT_SIZE
    print(f"  (envmap.exr is {h}x{w}; README.txt says how to open both in Blender)")
    return 0
