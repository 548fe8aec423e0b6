"""``nefii synth SCENE --out DIR``: render a built-in ground-truth scene with Mitsuba 3.

Writes training and test views (EXR and PNG), per-test-view ground-truth maps (albedo,
roughness, specular and diffuse layers, normals, depth, mask), relit test views under two
other environments, the mesh, the environment map and scene.json: the layout of
docs/datasets.md. The folder appears whole or not at all. ``nefii synth --list`` names
the scenes. Needs the ``synth`` extra (``pip install 'nefii[synth]'``); with libLLVM 19
installed Mitsuba runs its fast ``llvm_ad_rgb`` variant.
"""
from __future__ import annotations

import argparse
import dataclasses
import tempfile
import time
from pathlib import Path

from ..errors import InputError


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("synth", help="render a built-in ground-truth scene with Mitsuba 3",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("scene", nargs="?", metavar="SCENE", help="built-in scene name (see --list)")
    p.add_argument("--list", action="store_true", help="list the built-in scenes, one line each, and exit")
    p.add_argument("--out", type=Path, default=None, help="output folder (default: scenes/SCENE, or scenes/SCENE@ENV with --env)")
    p.add_argument("--res", type=int, default=256, help="image width and height in pixels (default 256)")
    p.add_argument("--views", type=int, default=100, help="training views (default 100)")
    p.add_argument("--test-views", type=int, default=20, help="test views, with ground-truth maps (default 20)")
    p.add_argument("--spp", type=int, default=256, help="samples per pixel (default 256; no clamping)")
    p.add_argument("--seed", type=int, default=0, help="seeds camera placement and sampling (default 0)")
    p.add_argument("--env", default="", metavar="NAME",
                   help="light the scene by another built-in environment (noon, sunset, overcast, studio) instead "
                        "of its own: the same object, views and materials under another light")
    p.add_argument("--env-height", type=int, default=1024,
                   help="rows of envmap.exr and relight maps, columns twice that (default 1024)")
    p.add_argument("--photo", action="store_true",
                   help="also photograph it as a phone would: OUT/clean is the scene, OUT/photo the capture "
                        "(8-bit JPEG, clipped highlights, per-view exposure and white balance, lens distortion, "
                        "noise, no masks; nerfstudio transforms.json). Score a fit of OUT/photo with "
                        "`nefii eval RUN --data OUT/clean`")
    p.add_argument("--photo-scale", type=int, default=2, metavar="S",
                   help="--photo: the photos are taken at S times --res (the scene is rendered again at that "
                        "resolution, ~S^2 times the time), as a camera with more pixels than the fit uses; "
                        "1 resamples the clean renders (blurrier). Default 2")
    p.set_defaults(func=run)


def list_scenes() -> list[str]:
    """One line per built-in scene: name, lighting, summary."""
    from ..synth.scenes import SCENES
    from ..synth.skies import get_environment

    width = max(len(n) for n in SCENES)
    lines = []
    for name, spec in SCENES.items():
        env = get_environment(spec.environment)
        lines.append(f"{name:<{width}}  {env.name} ({env.lighting}); {spec.summary}")
    return lines


def run(args: argparse.Namespace) -> int:
    if args.list:
        print("\n".join(list_scenes()))
        return 0
    if not args.scene:
        raise InputError(None, "name a SCENE to render, or use --list to see them")
    from ..synth.generate import SynthSettings, synthesize

    settings = SynthSettings(scene=args.scene, res=args.res, views=args.views, test_views=args.test_views,
                             spp=args.spp, seed=args.seed, env_height=args.env_height, environment=args.env)
    settings.validate()
    default_name = f"{args.scene}@{args.env}" if args.env else args.scene
    out = args.out if args.out is not None else Path("scenes") / default_name
    t0 = time.time()
    clean = out / "clean" if args.photo else out
    synthesize(settings, clean)
    lit = f", lit by {args.env}" if args.env else ""
    print(f"nefii synth: wrote {clean} ({settings.views} train + {settings.test_views} test views{lit}, "
          f"{settings.res}x{settings.res}, {settings.spp} spp) in {time.time() - t0:.0f} s")
    if args.photo:
        from ..synth.photo import PhotoSettings, make_photos

        if args.photo_scale < 1:
            raise InputError(None, f"--photo-scale must be 1 or more, got {args.photo_scale}")
        with tempfile.TemporaryDirectory(dir=out, prefix=".photo_render") as tmp:
            render = None
            if args.photo_scale > 1:
                render = Path(tmp) / "render"
                synthesize(dataclasses.replace(settings, res=settings.res * args.photo_scale), render)
            make_photos(clean, out / "photo", PhotoSettings(seed=args.seed), render=render)
        size = settings.res * args.photo_scale
        print(f"nefii synth: wrote {out / 'photo'} (the same views as a phone's {size}x{size} JPEGs; nerfstudio "
              f"transforms.json; a fit averages them down to {settings.res} px with --set max_image_side={settings.res})")
    return 0
