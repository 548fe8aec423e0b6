"""``nefii eval RUN``: render every test view and score it as the paper's Table 1 does.

Each view is kept as it is scored: an eval stopped part way (Ctrl-C, a lost session) goes on from the views it
had scored when run again with the same settings."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from tqdm import tqdm

from ..data import load_scene
from ..data.downscale import downscaled
from ..errors import InputError
from ..evaluate.run import evaluate_run
from ..fit.outputs import load_run
from ..io.lock import RunLock
from .common import add_threads_flag, pick_device, render_flags, set_threads


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("eval", help="render the test views and compute the Table 1 metrics", description=__doc__)
    p.add_argument("run", type=Path, help="run folder written by `nefii fit`")
    p.add_argument("--data", type=Path, default=None, help="dataset with the test split (default: the fitted one)")
    p.add_argument("--spp", type=int, default=256,
                   help="estimator samples per pixel; each draws one cosine, one GGX and one SG direction")
    p.add_argument("--device", default="auto", help="cpu | cuda | auto")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--material-only", action="store_true",
                   help="score the albedo and roughness only (no colour is path-traced, so --spp is unused and the "
                        "specular and RGB columns are empty): seconds a view instead of minutes at high resolution")
    p.add_argument("--max-views", type=int, default=0, metavar="N",
                   help="score N test views spread evenly over the test split (default 0: all of them)")
    add_threads_flag(p)
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    render_flags(args)
    if args.max_views < 0:
        raise InputError(None, f"--max-views: {args.max_views} is negative (0 scores every test view)")
    device = pick_device(args.device)
    fitted = load_run(args.run, device)
    set_threads(fitted.config.threads if args.threads is None else args.threads)
    scene = downscaled(load_scene(args.data or fitted.data, "test"), fitted.config.max_image_side)[0]
    gt = scene.ground_truth
    if args.material_only and (gt is None or (gt.albedo is None and gt.roughness is None)):
        raise InputError(scene.root, "--material-only: the test split has no ground-truth albedo or roughness "
                                     "maps to score (drop the flag to score the colour)")
    lock = RunLock(args.run, "eval")            # one writer at a time: two evals would share their partial views
    lock.acquire(warn=lambda line: print(f"nefii eval: warning: {line}"))
    try:
        evaluate_run(fitted, scene, args.run / "eval", 0 if args.material_only else args.spp, args.seed,
                     args.max_views,
                     progress=lambda it: tqdm(it, desc="eval", unit="view", disable=args.quiet), say=print)
    except KeyboardInterrupt:
        print("nefii eval: the views scored so far are kept; the same command goes on from them", file=sys.stderr)
        raise
    finally:
        lock.release()
    print((args.run / "eval" / "metrics.md").read_text())
    print(f"nefii eval: per-view EXRs and GT | ours | error grids in {args.run / 'eval'}")
    return 0
