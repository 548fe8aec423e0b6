"""``nefii relight RUN --envmap FILE | --dataset-lights``: render the fitted object under other light by path
tracing.

``--envmap FILE`` renders the test views (or ``--cameras``) under that map; ``OUT/<env>/`` is named by the
file's stem, with ``_rot<DEG>`` / ``_ev<EV>`` appended when turned or exposed. ``--dataset-lights`` renders
every relit set of the dataset's test split under the dataset's own maps into ``OUT/<set>/``: nefii's
``relight/<env>/`` under ``relight/<env>.exr``, Stanford-ORB's photographs of the object in its other scenes
(``transforms_novel.json``) each at its own pose under its own measured map.

Writes ``K.exr`` (linear RGBA, premultiplied: coverage in A, background 0, as the dataset's images) and
``K.png`` (sRGB with highlights rolled off, straight alpha) for every view ``K``, and ``render.json`` (what
was rendered, with the albedo scale). ``OUT`` is ``RUN/relight`` unless ``--out`` says otherwise. Where there
is ground truth (``--envmap``: the dataset's relit views of the same name, map neither turned nor exposed),
each view's PSNR and SSIM and Stanford-ORB's PSNR-H and PSNR-L go into ``OUT/metrics.json`` under the
folder's name (other entries kept), with ``K_grid.png`` (GT | relit | error x4); ``--dataset-lights`` adds
``dataset_lights``, the means over all its views (for Stanford-ORB: the benchmark's per-scene relighting score).
Each folder appears whole when its last view is done; the views done before a stop are kept, and the same command
goes on from them (every view renders from a seed of its own: a resumed folder is the uninterrupted one's).
"""
from __future__ import annotations

import argparse
import json
import sys
import warnings
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from ..data import load_scene
from ..data.downscale import downscaled
from ..data.fingerprint import arrays_sha256, cameras_sha256
from ..data.scene import Relit
from ..errors import InputError
from ..evaluate.outputs import write_grid
from ..evaluate.partial import PartialViews, model_sha256, view_seed
from ..evaluate.stanford_orb import PROTOCOL as ORB_PROTOCOL, relight_scores
from ..fit.model import decode_material
from ..fit.outputs import load_run
from ..io.atomic import write_text_atomic
from ..io.exr import write_exr
from ..io.images import write_png
from ..relight.environment import load_environment
from ..render.brdf import Material
from ..relight.pathtracer import PathSettings
from ..relight.render import render_relit
from ..relight.scoring import (PROTOCOL, albedo_scale_from_eval, albedo_scale_from_ground_truth, merge_metrics,
                              metrics_entry, scaled_material, score_view, tone_map)
from ..relight.cameras import Views, views_from_transforms
from ..relight.sets import RelightSet, dataset_sets, scoring_masks
from .common import add_threads_flag, pick_device, render_flags, set_threads


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("relight", help="render the fitted object under a new environment map (path tracing)",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("run", type=Path, help="run folder written by `nefii fit`")
    light = p.add_mutually_exclusive_group(required=True)
    light.add_argument("--envmap", type=Path, metavar="FILE",
                       help="equirectangular HDR environment (.exr or .hdr), in nefii's mapping (docs/design.md)")
    light.add_argument("--dataset-lights", action="store_true",
                       help="render every relit set of the dataset's test split under the dataset's own maps and "
                            "score it (nefii relight/<env>/; Stanford-ORB transforms_novel.json)")
    p.add_argument("--rotate", type=float, default=0.0, metavar="DEG",
                   help="turn the environment about world +Z by DEG degrees, counter-clockwise seen from above "
                        "(a light at azimuth phi moves to phi + DEG)")
    p.add_argument("--exposure", type=float, default=0.0, metavar="EV", help="scale the radiance by 2^EV (linear)")
    p.add_argument("--out", type=Path, default=None, metavar="DIR", help="output folder (default RUN/relight)")
    p.add_argument("--spp", type=int, default=256, metavar="N", help="paths per pixel (default 256)")
    p.add_argument("--max-bounces", type=int, default=8, metavar="N",
                   help="surface interactions per path (default 8; 1: direct light only)")
    p.add_argument("--cameras", type=Path, default=None, metavar="JSON",
                   help="render these cameras (a NeRF-style transforms.json) instead of the test views")
    p.add_argument("--data", type=Path, default=None, metavar="DIR",
                   help="dataset with the test split (default: the fitted one)")
    p.add_argument("--albedo-scale", choices=("auto", "none"), default="auto",
                   help="auto: apply the albedo scale eval found (or the same computed against ground-truth "
                        "albedo); none: the fitted albedo as it is")
    p.add_argument("--device", default="auto", help="cpu | cuda | auto")
    p.add_argument("--seed", type=int, default=0)
    add_threads_flag(p)
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def env_name(path: Path, rotate: float, exposure: float) -> str:
    name = path.stem
    if rotate:
        name += f"_rot{rotate:g}"
    if exposure:
        name += f"_ev{exposure:+g}"
    return name


def _warn(caught: list[warnings.WarningMessage]) -> None:
    for w in caught:
        print(f"nefii relight: warning: {w.message}")


def _check_modes(args: argparse.Namespace) -> None:
    if args.dataset_lights:
        for flag, given in (("--rotate", args.rotate), ("--exposure", args.exposure), ("--cameras", args.cameras)):
            if given:
                raise InputError(None, f"{flag}: not with --dataset-lights (the dataset's maps and views are used "
                                       "as they are)")


def _file_set(args: argparse.Namespace, env, scene, views: Views, name: str) -> RelightSet:
    """``--envmap``: every view under the file's map; scored against the dataset's same views relit under a map
    of the file's stem, when the map is neither turned nor exposed."""
    gt = None
    if scene is not None:
        gt = next((r for r in scene.relit if r.name == args.envmap.stem and r.cameras is None), None)
        if gt is not None and (args.rotate or args.exposure):
            print(f"nefii relight: not scored against the dataset's '{gt.name}': the map is turned or exposed")
            gt = None
        _check_same_map(gt, env.image)
    return RelightSet(name, views, lambda v: env, str(args.envmap), env.image, None if gt is None else gt.images,
                      None if gt is None else scoring_masks(scene))


def run(args: argparse.Namespace) -> int:
    render_flags(args)
    _check_modes(args)
    if args.out is not None and args.out.exists() and not args.out.is_dir():
        raise InputError(args.out, "exists and is not a folder: --out wants a folder")
    device = pick_device(args.device)
    env = None
    if args.envmap is not None:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            env = load_environment(args.envmap, args.rotate, args.exposure, device)
        _warn(caught)
    fitted = load_run(args.run, device)
    set_threads(fitted.config.threads if args.threads is None else args.threads)
    geometry = fitted.open_geometry()

    # ---- what to render: the views, the light of each, the truth to score against
    scene = None
    if args.cameras is None:
        scene = downscaled(load_scene(args.data or fitted.data, "test"), fitted.config.max_image_side)[0]
    if args.dataset_lights:
        sets = dataset_sets(scene, device)
    else:
        views = views_from_transforms(args.cameras) if scene is None else Views(scene.cameras, scene.indices)
        sets = [_file_set(args, env, scene, views, env_name(args.envmap, args.rotate, args.exposure))]

    # ---- the albedo scale
    model = fitted.model

    def material(x: torch.Tensor, lookup_normal: torch.Tensor) -> Material:
        return decode_material(model, x, lookup_normal)

    scale, source = None, "none (--albedo-scale none)"
    if args.albedo_scale == "auto":
        scale = albedo_scale_from_eval(args.run)
        source = f"mean of the per-view albedo_scale in {args.run / 'eval' / 'metrics.json'}"
        if scale is None and scene is not None:
            scale = albedo_scale_from_ground_truth(material, geometry, scene, device)
            source = "median(gt / pred) albedo per test view over the mask, mean over views (eval has not run)"
        if scale is None:
            source = "none: eval has not run and the dataset has no ground-truth albedo"
    material = scaled_material(material, scale)
    stated = [float(s) for s in (np.ones(3) if scale is None else scale)]

    # ---- render every view of every set, score where there is ground truth
    settings = PathSettings(max_bounces=args.max_bounces, ray_offset=fitted.config.ray_offset)
    out_root = args.out or args.run / "relight"
    key = {"model": model_sha256(model), "rotate": args.rotate, "exposure": args.exposure, "spp": args.spp,
           "max_bounces": args.max_bounces, "seed": args.seed, "albedo_scale": stated, "device": device.type}
    every = []
    for rs in sets:
        try:
            scores = _render_set(rs, geometry, material, settings, device, key, out_root, args, stated, source)
        except KeyboardInterrupt:
            print("nefii relight: the views rendered so far are kept; the same command goes on from them",
                  file=sys.stderr)
            raise
        every += scores
        if scores:
            entry = metrics_entry(scores, albedo_scale=stated, albedo_scale_source=source, spp=args.spp,
                                  max_bounces=args.max_bounces, envmap=rs.envmap,
                                  protocol=f"{PROTOCOL}; {ORB_PROTOCOL}")
            merge_metrics(out_root / "metrics.json", rs.name, entry)
            print(f"nefii relight: {rs.name}: PSNR {_fmt(entry['psnr'], 2)} dB, SSIM {_fmt(entry['ssim'], 4)}, "
                  f"PSNR-H {_fmt(entry['psnr_h'], 2)} dB, PSNR-L {_fmt(entry['psnr_l'], 2)} dB over {len(scores)} "
                  f"views -> {out_root / 'metrics.json'}")
        print(f"nefii relight: {len(rs.views.cameras)} views in {out_root / rs.name}")
    if args.dataset_lights and every:
        summary = metrics_entry(every, sets=[rs.name for rs in sets], format=scene.format, albedo_scale=stated,
                                albedo_scale_source=source, spp=args.spp, max_bounces=args.max_bounces,
                                protocol=f"means over every view of every set; {PROTOCOL}; {ORB_PROTOCOL}")
        summary.pop("views")
        summary["view_count"] = len(every)
        merge_metrics(out_root / "metrics.json", DATASET_LIGHTS, summary)
        print(f"nefii relight: all {len(every)} views: PSNR-H {_fmt(summary['psnr_h'], 2)} dB, "
              f"PSNR-L {_fmt(summary['psnr_l'], 2)} dB")
    print(f"nefii relight: albedo scale {np.round(stated, 4).tolist()} ({source})")
    return 0


DATASET_LIGHTS = "dataset_lights"
"""the ``metrics.json`` entry of ``--dataset-lights``: means over all its views"""


def _set_key(rs: RelightSet, key: dict) -> str:
    """What ``rs``'s renders depend on, as JSON: ``key`` (model and settings), the views and their lights."""
    return json.dumps({**key, "set": rs.name, "envmap": rs.envmap,
                       "radiance": arrays_sha256(rs.radiance.detach().cpu().numpy()),
                       "cameras": cameras_sha256(rs.views.cameras), "views": [int(k) for k in rs.views.indices]},
                      sort_keys=True)


def _render_set(rs: RelightSet, geometry, material, settings: PathSettings, device: torch.device, key: dict,
                out_root: Path, args: argparse.Namespace, stated: list[float], source: str) -> list[dict]:
    """Render ``rs`` into ``out_root / rs.name`` (whole at the end; each view kept as it is done, so a rerun goes
    on from them: :mod:`nefii.evaluate.partial`); the per-view scores where it has ground truth."""
    cams = rs.views.cameras
    partial = PartialViews(out_root / rs.name, _set_key(rs, key))
    out = partial.folder
    done = {v: partial.done(rs.views.indices[v]) for v in range(len(cams))}
    resumed = sum(d is not None for d in done.values())
    if resumed:
        print(f"nefii relight: {rs.name}: {resumed} of {len(cams)} views already rendered by an interrupted "
              f"relight ({out}); rendering the rest")
    todo = [v for v in range(len(cams)) if done[v] is None]
    for v in tqdm(todo, desc=f"relight {rs.name}", unit="view", disable=args.quiet):
        k = rs.views.indices[v]
        g = torch.Generator(device=device).manual_seed(view_seed(args.seed, int(k)))
        img = render_relit(geometry, material, rs.light(v), cams.c2w[v], cams.K[v], cams.height, cams.width,
                           args.spp, g, settings)
        rgb = img.rgb.cpu().numpy()
        alpha = img.coverage.cpu().numpy()[..., None]
        write_exr(out / f"{k}.exr", np.concatenate([img.premultiplied.cpu().numpy(), alpha], -1))
        write_png(out / f"{k}.png", np.concatenate([tone_map(rgb), alpha], -1))
        done[v] = {}
        if rs.truth is not None:
            truth = rs.truth[v].numpy()
            mask = rs.masks[v].numpy() if rs.masks is not None else alpha[..., 0] > 0.5
            p, s = score_view(rgb, truth, mask)
            done[v] = {"index": k, "psnr": p, "ssim": s, **relight_scores(rgb, truth, mask)}
            write_grid(out / f"{k}_grid.png", [(truth, rgb)], [True])
        partial.commit(k, done[v])
    info = {"envmap": rs.envmap, "rotate_deg": args.rotate, "exposure_ev": args.exposure,
            "spp": args.spp, "max_bounces": args.max_bounces, "rr_depth": settings.rr_depth,
            "seed": args.seed, "views": len(cams), "albedo_scale": stated, "albedo_scale_source": source,
            "images": "K.exr linear RGBA premultiplied (A = coverage); K.png sRGB, highlights rolled off "
                      "above linear 0.8, straight alpha"}
    write_text_atomic(out / "render.json", json.dumps(info, indent=2) + "\n")
    partial.finish()
    return [done[v] for v in range(len(cams)) if done[v]]


def _fmt(x: float | None, digits: int) -> str:
    return "n/a" if x is None else f"{x:.{digits}f}"


def _check_same_map(gt: Relit | None, image: torch.Tensor) -> None:
    """Warn when the dataset's own copy of the map differs from the file given (scored all the same)."""
    if gt is None or gt.envmap is None:
        return
    mine = image.cpu()
    if gt.envmap.shape != mine.shape or not torch.allclose(gt.envmap, mine, rtol=0.02, atol=1e-4):
        print(f"nefii relight: warning: the map differs from the dataset's relight/{gt.name} environment; "
              "scoring against its images all the same")
