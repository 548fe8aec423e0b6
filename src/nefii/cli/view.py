"""``nefii view RUN``: one self-contained HTML page showing the exported asset under the recovered
light, with orbit controls and albedo / roughness / shaded toggles. Opens offline from disk.

The asset is baked as ``nefii export`` bakes it (or taken from ``--asset``); three.js is the
pinned npm release, found in the cache or fetched once with npm (see ``nefii.export.three``)."""
from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

from ..errors import InputError
from ..export.asset import environment_image, glb_bytes
from ..export.three import locate_three
from ..export.viewer import build_page, default_exposure
from ..fit.outputs import load_run
from ..io.atomic import write_text_atomic
from ..io.exr import write_exr
from .common import pick_device, set_threads
from .export import bake_with_progress, check_writable, texture_size

VIEW_ENVMAP_SIZE = (256, 512)


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("view", help="write a self-contained HTML viewer of the exported asset", description=__doc__)
    p.add_argument("run", type=Path, help="run folder written by `nefii fit`")
    p.add_argument("--out", type=Path, default=None, help="HTML file (default: RUN/view.html)")
    p.add_argument("--asset", type=Path, default=None, help="a GLB from `nefii export` (default: bake one now)")
    p.add_argument("--texture-size", default="1024", metavar="N", help="texture side when baking (default 1024)")
    p.add_argument("--three", type=Path, default=None,
                   help="three.js npm tarball or package folder (default: $NEFII_THREE, then the cache)")
    p.add_argument("--device", default="auto", help="cpu | cuda | auto")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    size = texture_size(args.texture_size)
    out = args.out or args.run / "view.html"
    if out.suffix.lower() not in (".html", ".htm"):
        raise InputError(out, "the page's file name should end in .html")
    check_writable(out)
    if args.asset is not None:
        if not args.asset.is_file():
            raise InputError(args.asset, "not found")
        with open(args.asset, "rb") as f:
            if f.read(4) != b"glTF":
                raise InputError(args.asset, "not a binary glTF (.glb), e.g. from `nefii export`")
    fitted = load_run(args.run, pick_device(args.device))
    three = locate_three(args.three, log=lambda s: print(f"nefii view: {s}"))
    set_threads(fitted.config.threads)
    if args.asset is not None:
        glb = args.asset.read_bytes()
    else:
        mesh = fitted.geometry.open_mesh(threads=1)
        glb = glb_bytes(bake_with_progress(fitted.model, mesh, size, args.quiet))
    env = environment_image(fitted.model, VIEW_ENVMAP_SIZE)
    with tempfile.TemporaryDirectory() as tmp:
        write_exr(Path(tmp) / "env.exr", env)
        env_exr = (Path(tmp) / "env.exr").read_bytes()
    page = build_page(glb, env_exr, default_exposure(env), f"nefii view: {args.run.resolve().name}", three)
    write_text_atomic(out, page)
    print(f"nefii view: wrote {out} ({len(page) / 2**20:.1f} MB, self-contained); open it in a browser")
    return 0
