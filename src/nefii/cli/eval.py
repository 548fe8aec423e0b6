"""``nefii eval RUN``: render every test view and score it as the paper's Table 1 does."""
from __future__ import annotations

import argparse
from pathlib import Path

import torch
from tqdm import tqdm

from ..data import load_scene
from ..data.downscale import downscaled
from ..evaluate.run import evaluate_run
from ..fit.outputs import load_run
from .common import add_threads_flag, pick_device, render_flags, set_threads


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("eval", help="render the test views and compute the Table 1 metrics", description=__doc__)
    p.add_argument("run", type=Path, help="run folder written by `nefii fit`")
    p.add_argument("--data", type=Path, default=None, help="dataset with the test split (default: the fitted one)")
    p.add_argument("--spp", type=int, default=256,
                   help="estimator samples per pixel; each draws one cosine, one GGX and one SG direction")
    p.add_argument("--device", default="auto", help="cpu | cuda | auto")
    p.add_argument("--seed", type=int, default=0)
    add_threads_flag(p)
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    render_flags(args)
    device = pick_device(args.device)
    fitted = load_run(args.run, device)
    set_threads(fitted.config.threads if args.threads is None else args.threads)
    scene = downscaled(load_scene(args.data or fitted.data, "test"), fitted.config.max_image_side)[0]
    g = torch.Generator(device=device).manual_seed(args.seed)
    evaluate_run(fitted, scene, args.run / "eval", args.spp, g,
                 progress=lambda it: tqdm(it, desc="eval", unit="view", disable=args.quiet))
    print((args.run / "eval" / "metrics.md").read_text())
    print(f"nefii eval: per-view EXRs and GT | ours | error grids in {args.run / 'eval'}")
    return 0
