"""``benchmarks/results/peers.md`` and ``peers.png`` from the cached runs (nothing is fitted here):

    python -m benchmarks.peers.report [--scenes bowl cup]

(``python -m benchmarks.peers.mitsuba_inverse`` fits what is missing and ends by writing them.) Rows
per scene: nefii full, env-map grid and PhySG-style (``benchmarks.quality``'s runs), the Mitsuba peer
(its ``result.json``) and a constant-albedo reference; the chart is albedo PSNR against fitting time.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .. import common, quality
from .mitsuba_peer import PeerConfig
from .nefii_curve import read_curve_csv

SCENES = ("bowl", "cup", "leaning", "corner")
NEFII_ROWS = (("full", "nefii full"), ("light_envmap", "nefii env-map grid"), ("physg", "nefii PhySG-style"))
PEER = "Mitsuba 3 prb"
REFERENCE = "constant albedo (reference)"
COLUMNS = (  # key, label, format
    ("albedo_psnr", "albedo PSNR", "{:.2f}"),
    ("albedo_ssim", "albedo SSIM", "{:.4f}"),
    ("roughness_mse", "roughness MSE", "{:.4f}"),
    ("specular_psnr", "specular PSNR", "{:.2f}"),
    ("rgb_psnr", "novel-view PSNR", "{:.2f}"),
    ("rgb_psnr_whole", "novel-view PSNR (whole image)", "{:.2f}"),
    ("fit_min", "wall min", "{:.1f}"),
    ("peak_gib", "peak GiB", "{:.2f}"),
)


def peer_dir(name: str) -> Path:
    """The peer's fit and nefii's curve for scene ``name``."""
    return common.CACHE / "peers" / name


@dataclass(frozen=True)
class Row:
    system: str
    values: dict[str, float | None]
    threads: int | None
    code: str
    note: str = ""


def nefii_row(scene: str, config: str, label: str) -> Row | None:
    """A completed ``benchmarks.quality`` run as a row."""
    r = quality.read_row(scene, config)
    if r is None:
        return None
    vals = {k: r.get(k) for k, *_ in COLUMNS}
    vals.update(rgb_psnr_whole=r["whole"]["rgb_psnr"], fit_min=r["fit_s"] / 60.0, peak_gib=r["peak_gib"])
    return Row(label, vals, r.get("threads"), r.get("code", "unknown"))


def peer_rows(result_file: Path) -> list[Row]:
    """The peer's row and the constant-albedo reference row from its ``result.json``."""
    if not result_file.is_file():
        return []
    res = json.loads(result_file.read_text())
    m, w = res["eval"]["masked"], res["eval"]["whole_image"]
    vals = {k: m.get(k) for k, *_ in COLUMNS}
    vals.update(rgb_psnr_whole=w["rgb_psnr"], fit_min=res["fit_s"] / 60.0, peak_gib=res["peak_rss_gib_fit"])
    ref = {k: None for k, *_ in COLUMNS} | res["reference"]["constant_albedo"]
    return [Row(PEER, vals, res["config"]["threads"], res["code"], f"{res['steps']} steps"),
            Row(REFERENCE, ref, None, "", "albedo 0.5, roughness 0.5 everywhere")]


def table(rows: list[Row]) -> list[str]:
    def cell(v: float | None, fmt: str) -> str:
        return "n/a" if v is None or (isinstance(v, float) and math.isnan(v)) else fmt.format(v)

    lines = ["| system | " + " | ".join(c[1] for c in COLUMNS) + " | threads | code | note |",
             "|---|" + "---|" * (len(COLUMNS) + 3)]
    for r in rows:
        vals = [cell(r.values.get(k), fmt) for k, _, fmt in COLUMNS]
        lines.append(f"| {r.system} | " + " | ".join(vals) + f" | {r.threads or ''} | {r.code} | {r.note} |")
    return lines


def plot(path: Path, scenes: list[str], reference: dict[str, float | None]) -> bool:
    """Albedo PSNR against fitting minutes, one panel per scene with nefii's and the peer's curves."""
    from matplotlib.figure import Figure

    files = (("nefii full", "nefii_curve.csv"), (PEER, "curve.csv"))
    curves = {s: {label: read_curve_csv(peer_dir(s) / f) for label, f in files if (peer_dir(s) / f).is_file()}
              for s in scenes}
    curves = {s: c for s, c in curves.items() if c}
    if not curves:
        return False
    fig = Figure(figsize=(5.2 * len(curves), 4.0), layout="constrained")
    for ax, (s, by_system) in zip(fig.subplots(1, len(curves), squeeze=False)[0], curves.items()):
        for label, c in by_system.items():
            ok = ~np.isnan(c["albedo_psnr"])
            ax.plot(c["fit_s"][ok] / 60.0, c["albedo_psnr"][ok], label=label, marker="o" if ok.sum() == 1 else None)
        if reference.get(s) is not None:
            ax.axhline(reference[s], color="grey", linestyle="--", label=REFERENCE)
        ax.set(title=s, xlabel="fitting time (min)", ylabel="albedo PSNR (dB, masked, aligned)")
        ax.grid(alpha=0.3)
        ax.legend(loc="best")
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)
    return True


def write_report(scenes: list[str], command: str | None = None, elapsed_s: float | None = None) -> None:
    """peers.md (and peers.png) for ``scenes`` from whatever is cached; ``command`` made the runs."""
    order = list(dict.fromkeys([*SCENES, *scenes]))
    per_scene = {}
    for s in order:
        rows = [r for c, label in NEFII_ROWS if (r := nefii_row(s, c, label)) is not None]
        rows += peer_rows(peer_dir(s) / "result.json")
        if any(r.system == PEER for r in rows):
            per_scene[s] = rows
    results = {s: json.loads((peer_dir(s) / "result.json").read_text()) for s in per_scene}
    reference = {s: next(r.values["albedo_psnr"] for r in rows if r.system == REFERENCE)
                 for s, rows in per_scene.items()}
    plotted = plot(common.RESULTS / "peers.png", list(per_scene), reference)
    command = command or "python -m benchmarks.peers.mitsuba_inverse --scenes " + " ".join(scenes)
    first = next(iter(results.values()), None)
    lines = [f"# peers: nefii and Mitsuba 3 inverse rendering ({common.stamp()})", "",
             f"Machine: {common.machine()}"
             + ("".join(f"; {k} {v}" for k, v in first["versions"].items()) if first else "") + ".",
             f"Made by `{command}` (from the repository root; runs cached in benchmarks/.cache)"
             + (f" in {elapsed_s / 60:.1f} min" if elapsed_s is not None else "")
             + f"; current code {common.code_version()}.", "",
             "Every row is scored by nefii's eval code (`nefii.evaluate.run`: masked block, albedo aligned per view "
             "and channel by median(gt/pred)) on the same test views against the same mesh, each pixel's material the "
             "mean over 4 x 4 sub-pixel rays as the ground truth's layers are: `nefii eval`'s for the nefii rows, "
             "`benchmarks.peers.hits` for the peer's textures and both albedo-over-time curves. "
             "nefii rows: `benchmarks.quality` runs (`cpu` preset; env-map grid = `light.kind=envmap`; PhySG-style "
             "= `visibility=off indirect=off`). The peer: Mitsuba's `prb` (llvm_ad_rgb) optimising a principled "
             "BSDF's base-colour and roughness textures over the xatlas atlas of `nefii export` and a "
             "low-resolution env map (log radiance, total-variation prior) with Adam, for the wall-clock time of "
             "nefii full's fit; its albedo/roughness are its textures at the test hits, its novel views Mitsuba "
             "renders of the recovered scene. Wall time: fitting only; peak GiB: the fitting process's peak RSS.",
             ""]
    if first is not None:
        settings = ", ".join(f"{f.name}={first['config'].get(f.name)}" for f in dataclasses.fields(PeerConfig))
        lines += [f"Peer settings (`PeerConfig`, picked by a few 60-second trials on bowl): {settings}; eval at "
                  f"{first['eval_spp']} spp.", ""]
    for s, rows in per_scene.items():
        lines += [f"## {s}", "", *table(rows), ""]
    if plotted:
        lines += ["## Albedo PSNR against fitting time", "", "![albedo PSNR against time](peers.png)", "",
                  "nefii's curve is the full fit re-run in process with snapshots (`benchmarks.peers.nefii_curve`, "
                  "same recipe and seed); the peer's is its own run. Both are evaluated off the clock.", ""]
    missing = [f"{s}/{label}" for s in scenes for c, label in NEFII_ROWS if quality.read_row(s, c) is None]
    missing += [f"{s}/{PEER}" for s in scenes if not (peer_dir(s) / "result.json").is_file()]
    if missing:
        lines += ["Not run yet: " + ", ".join(missing) + "."]
    common.write_results("peers.md", lines)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", nargs="+", default=list(SCENES[:2]))
    write_report(ap.parse_args(argv).scenes)


if __name__ == "__main__":
    main()
