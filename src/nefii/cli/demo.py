"""``nefii demo``: the whole pipeline on the smallest built-in scene.

1. ``nefii synth`` renders the scene with Mitsuba (once; kept in ``OUT/scene``),
2. ``nefii fit`` recovers albedo, roughness, the SG environment and the radiance cache
   (``cpu`` preset; an interrupted demo resumes from its last checkpoint),
3. ``nefii eval`` scores the test views as the paper's Table 1 and writes the images.
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

from .main import main as nefii


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("demo", help="synthesise the smallest built-in scene, fit it, evaluate it", description=__doc__,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", type=Path, default=Path("demo_out"), help="output folder (default: demo_out)")
    p.add_argument("--scene", default=None, help="built-in scene (default: the smallest)")
    p.add_argument("--res", type=int, default=128, help="image side in pixels (default 128)")
    p.add_argument("--views", type=int, default=64, help="training views (default 64)")
    p.add_argument("--test-views", type=int, default=8, help="test views (default 8)")
    p.add_argument("--spp", type=int, default=64, help="samples per pixel of the ground truth and of eval")
    p.add_argument("--preset", default="cpu", help="fit preset (default cpu)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="fit config overrides, as for nefii fit")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from ..synth import smallest_scene

    t0 = time.time()
    scene = args.scene or smallest_scene()
    data, run_dir = args.out / "scene", args.out / "run"
    if not (data / "transforms_train.json").exists():
        print(f"nefii demo: [1/3] synthesising the built-in scene '{scene}' into {data}")
        rc = nefii(["synth", scene, "--out", str(data), "--res", str(args.res), "--views", str(args.views),
                    "--test-views", str(args.test_views), "--spp", str(args.spp)])
        if rc:
            return rc
    else:
        print(f"nefii demo: [1/3] using the scene already in {data}")
    if not (run_dir / "model.pt").exists():
        resume = ["--resume"] if (run_dir / "checkpoints").exists() else []
        print(f"nefii demo: [2/3] fitting ({args.preset} preset) into {run_dir}")
        rc = nefii(["fit", str(data), "--out", str(run_dir), "--preset", args.preset, *resume,
                    *(x for kv in args.overrides for x in ("--set", kv))])
        if rc:
            return rc
    else:
        print(f"nefii demo: [2/3] using the fit already in {run_dir}")
    print("nefii demo: [3/3] evaluating the test views")
    rc = nefii(["eval", str(run_dir), "--spp", str(args.spp)])
    print(f"nefii demo: done in {(time.time() - t0) / 60:.1f} min. Images: {run_dir / 'eval'} "
          f"(GT | ours | error grids, per-view EXRs), recovered light: {run_dir / 'envmap.exr'}")
    return rc
