"""``benchmarks/results/peers.md`` and ``peers.png`` from the cached runs (nothing is fitted here).

Rows per scene: nefii full, nefii env-map grid, nefii PhySG-style (from ``benchmarks/quality.py``'s
run folders), the Mitsuba peer (its ``result.json``) and a constant-albedo reference. The verdict
paragraph is generated from the numbers: which row wins each column, and where the peer beats
nefii's full model.
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from nefii_curve import read_curve_csv

NEFII_ROWS = (("full", "nefii full"), ("light_envmap", "nefii env-map grid"), ("physg", "nefii PhySG-style"))
PEER = "Mitsuba 3 prb"
REFERENCE = "constant albedo (reference)"

COLUMNS = (  # key, label, better ("high" | "low"), format
    ("albedo_psnr", "albedo PSNR", "high", "{:.2f}"),
    ("albedo_ssim", "albedo SSIM", "high", "{:.4f}"),
    ("roughness_mse", "roughness MSE", "low", "{:.4f}"),
    ("specular_psnr", "specular PSNR", "high", "{:.2f}"),
    ("rgb_psnr", "novel-view PSNR", "high", "{:.2f}"),
    ("rgb_psnr_whole", "novel-view PSNR (whole image)", "high", "{:.2f}"),
    ("fit_min", "wall min", "low", "{:.1f}"),
    ("peak_gib", "peak GiB", "low", "{:.2f}"),
)
VERDICT_COLUMNS = ("albedo_psnr", "albedo_ssim", "roughness_mse", "rgb_psnr", "fit_min", "peak_gib")


@dataclass(frozen=True)
class Row:
    system: str
    values: dict[str, float | None]
    threads: int | None
    code: str
    note: str = ""


def nefii_row(read_row, scene: str, config: str, label: str) -> Row | None:
    """A completed quality.py run as a row (``read_row`` is quality.read_row)."""
    r = read_row(scene, config)
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
    ref = {k: None for k, *_ in COLUMNS}
    ref.update(res["reference"]["constant_albedo"])
    return [Row(PEER, vals, res["config"]["threads"], res["code"], f"{res['steps']} steps"),
            Row(REFERENCE, ref, None, "", "albedo 0.5, roughness 0.5 everywhere")]


def _fmt(v: float | None, fmt: str) -> str:
    return "n/a" if v is None or (isinstance(v, float) and math.isnan(v)) else fmt.format(v)


def table(rows: list[Row]) -> list[str]:
    lines = ["| system | " + " | ".join(c[1] for c in COLUMNS) + " | threads | code | note |",
             "|---|" + "---|" * (len(COLUMNS) + 3)]
    for r in rows:
        vals = [_fmt(r.values.get(k), fmt) for k, _, _, fmt in COLUMNS]
        lines.append(f"| {r.system} | " + " | ".join(vals) + f" | {r.threads or ''} | {r.code} | {r.note} |")
    return lines


NEAR = {"fit_min": 0.02, "peak_gib": 0.02}
"""columns where a relative gap this small counts as even (the peer's time is nefii's by construction)"""


def _compare(key: str, a: float, b: float, better: str, fmt: str) -> int:
    """+1 if ``a`` is better, -1 if worse, 0 if equal as printed (or within :data:`NEAR`)."""
    if fmt.format(a) == fmt.format(b) or abs(a - b) <= NEAR.get(key, 0.0) * max(abs(a), abs(b)):
        return 0
    return 1 if (a > b) == (better == "high") else -1


def verdict(scene: str, rows: list[Row]) -> str:
    """One generated paragraph: each column's winner, and the peer against nefii full column by column."""
    systems = [r for r in rows if r.system != REFERENCE]
    by = {r.system: r for r in systems}
    parts = []
    wins = []
    for key, label, better, fmt in COLUMNS:
        if key not in VERDICT_COLUMNS:
            continue
        have = [(r.values[key], r.system) for r in systems if r.values.get(key) is not None]
        if not have:
            continue
        best = max(have) if better == "high" else min(have)
        wins.append(f"{label}: {best[1]} ({fmt.format(best[0])})")
    parts.append(f"**{scene}** — best per column: " + "; ".join(wins) + ".")
    peer, full = by.get(PEER), by.get("nefii full")
    if peer is not None and full is not None:
        sides: dict[int, list[str]] = {1: [], -1: [], 0: []}
        for key, label, better, fmt in COLUMNS:
            a, b = peer.values.get(key), full.values.get(key)
            if a is None or b is None:
                continue
            sides[_compare(key, a, b, better, fmt)].append(f"{label} {fmt.format(a)} vs {fmt.format(b)}")
        if sides[1]:
            parts.append("The peer beats nefii full on " + "; ".join(sides[1]) + ".")
        if sides[-1]:
            parts.append("nefii full beats the peer on " + "; ".join(sides[-1]) + ".")
        if sides[0]:
            parts.append("Even (peer vs nefii full): " + "; ".join(sides[0]) + ".")
    ref = next((r for r in rows if r.system == REFERENCE), None)
    if ref is not None and ref.values.get("albedo_psnr") is not None:
        beat = [r.system for r in systems if (r.values.get("albedo_psnr") or -1) > ref.values["albedo_psnr"]]
        parts.append(f"Constant albedo scores {ref.values['albedo_psnr']:.2f} dB albedo PSNR; "
                     + (f"above it: {', '.join(beat)}." if beat else "no system beats it."))
    return " ".join(parts)


def crossing(curve_a: dict[str, np.ndarray], level: float) -> float | None:
    """First fitting time (s) at which ``curve_a``'s albedo PSNR reaches ``level``."""
    ok = np.nonzero(curve_a["albedo_psnr"] >= level)[0]
    return None if len(ok) == 0 else float(curve_a["fit_s"][ok[0]])


def _duration(seconds: float) -> str:
    return f"{seconds:.0f} s" if seconds < 60 else f"{seconds / 60:.1f} min"


def curve_sentence(scene: str, peer_csv: Path, nefii_csv: Path) -> str | None:
    if not (peer_csv.is_file() and nefii_csv.is_file()):
        return None
    peer, nef = read_curve_csv(peer_csv), read_curve_csv(nefii_csv)
    peer = {k: v[~np.isnan(peer["albedo_psnr"])] for k, v in peer.items()}
    if not len(peer["fit_s"]) or not len(nef["fit_s"]):
        return None
    nef_final, peer_final = float(nef["albedo_psnr"][-1]), float(peer["albedo_psnr"][-1])
    t_peer = crossing(peer, nef_final)
    t_nef = crossing(nef, peer_final)
    s = (f"{scene}: curve ends at {peer_final:.2f} dB (peer, {_duration(peer['fit_s'][-1])}) and "
         f"{nef_final:.2f} dB (nefii, {_duration(nef['fit_s'][-1])}); ")
    if t_peer is not None:
        s += f"the peer reaches nefii's final albedo PSNR after {_duration(t_peer)}"
    elif t_nef is not None:
        s += f"nefii reaches the peer's final albedo PSNR after {_duration(t_nef)}"
    else:
        s += "neither reaches the other's final value"
    return s + "."


def plot(path: Path, curves: dict[str, dict[str, Path]], finals: dict[str, dict[str, float]]) -> bool:
    """Albedo PSNR against fitting minutes, one panel per scene, nefii and the peer on each."""
    from chart import Panel, Series, draw_chart

    colours = {"nefii full": (31, 119, 180), PEER: (255, 127, 14)}
    panels = []
    for s, files in curves.items():
        panel = Panel(s)
        span = 0.0
        for label, f in files.items():
            if not f.is_file():
                continue
            c = read_curve_csv(f)
            ok = ~np.isnan(c["albedo_psnr"])
            panel.series.append(Series(label, c["fit_s"][ok] / 60.0, c["albedo_psnr"][ok], colours[label]))
            span = max(span, float(np.max(c["fit_s"][ok])) / 60.0 if ok.any() else 0.0)
        ref = finals.get(s, {}).get(REFERENCE)
        if panel.series and ref is not None:
            panel.series.append(Series(REFERENCE, np.array([0.0, span]), np.array([ref, ref]), (128, 128, 128),
                                       dashed=True))
        if panel.series:
            panels.append(panel)
    if not panels:
        return False
    draw_chart(path, panels, "fitting time (min, 1 thread)", "albedo PSNR (dB, masked, aligned)")
    return True
