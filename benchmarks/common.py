"""Shared by the benchmark scripts: machine facts, scene caching, results tables."""
from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import platform
import subprocess
import sys
import time
from collections.abc import Sequence
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parent
REPO = ROOT.parent
"""the repository root: where ``python -m benchmarks.<name>`` runs"""
CACHE = Path(os.environ.get("NEFII_BENCH_CACHE", ROOT / ".cache")).resolve()
"""scenes and runs; ``$NEFII_BENCH_CACHE`` points another checkout's benchmarks at the same cache"""
RESULTS = ROOT / "results"


def machine() -> str:
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    cores = len(os.sched_getaffinity(0))
    gpu = torch.cuda.get_device_name(0) if torch.cuda.is_available() else "no GPU"
    return f"{cpu}, {cores} cores, {gpu}; Python {platform.python_version()}, torch {torch.__version__}"


def scene(name: str, res: int = 128, views: int = 64, test_views: int = 8, spp: int = 64) -> Path:
    """A built-in scene, synthesised once into ``benchmarks/.cache`` (Mitsuba needed the first time);
    ``OBJECT@ENV`` is the scene's object under another built-in environment (``nefii synth --env``)."""
    out = CACHE / f"{name}_{res}_{views}_{test_views}_{spp}"
    if not (out / "transforms_train.json").exists():
        obj, _, env = name.partition("@")
        subprocess.run([sys.executable, "-m", "nefii.cli.main", "synth", obj, "--out", str(out), "--res", str(res),
                        "--views", str(views), "--test-views", str(test_views), "--spp", str(spp),
                        *(["--env", env] if env else [])], check=True)
    else:
        from nefii.synth.generate import synth_versions  # noqa: PLC0415

        stale = version_changes(out, synth_versions())
        if stale:
            print(f"benchmarks: {out.name} was synthesised with other code or libraries ({stale}); its figures "
                  f"may differ from a fresh cache's: delete it to make it again", file=sys.stderr)
    return out


def version_changes(scene_dir: Path, now: dict[str, str | None]) -> str:
    """The entries of ``scene_dir/scene.json``'s ``versions`` that differ from ``now``, as ``key old -> new``
    (comma-separated; a record without ``versions`` counts as every key unknown); '' when none do."""
    try:
        then = json.loads((scene_dir / "scene.json").read_text()).get("versions", {})
    except (OSError, ValueError):
        then = {}
    keys = [k for k in now if k != "platform"]
    return ", ".join(f"{k} {then.get(k)} -> {now[k]}" for k in keys if then.get(k) != now[k])


def fit_threads(threads: int | None, jobs: int) -> int:
    """Threads per fit: ``threads`` if given, else 1 when ``jobs`` fits share the machine, else 0 (all cores)."""
    return threads if threads is not None else (1 if jobs > 1 else 0)


def set_flags(overrides: list[str], threads: int) -> list[str]:
    """``--set KEY=VALUE`` arguments of a nefii command for ``overrides`` and the thread count."""
    return [x for kv in [*overrides, f"threads={threads}"] for x in ("--set", kv)]


def settings_digest(cfg: object, aside: Sequence[str]) -> str:
    """8 hex digits of a resolved config dataclass's settings, the fields ``aside`` left out: a cached run is reused
    only where they match, so neither a variant nor a run made at other defaults stands in for the one asked for."""
    kept = {k: v for k, v in dataclasses.asdict(cfg).items() if k not in aside}
    return hashlib.sha1(json.dumps(kept, sort_keys=True).encode()).hexdigest()[:8]


FIT_ASIDE = ("threads", "checkpoint_every_s", "preview_every")
"""fit settings that do not change what a fit computes"""


def fit_digest(overrides: Sequence[str], preset: str = "cpu") -> str:
    """:func:`settings_digest` of the fit settings ``preset`` and ``overrides`` resolve to (threads, checkpointing and
    previews aside)."""
    from nefii.fit.config import resolve_config

    return settings_digest(resolve_config(preset, list(overrides)), FIT_ASIDE)


def nefii(*args: str, what: str = "") -> None:
    """``nefii ARGS`` in a subprocess, its output captured; a failure raises naming ``what`` (default: the command)
    with the end of its stderr."""
    proc = subprocess.run([sys.executable, "-m", "nefii.cli.main", *args], capture_output=True, text=True)
    if proc.returncode != 0:
        raise RuntimeError(f"{what or 'nefii ' + ' '.join(args)} failed:\n{proc.stderr[-3000:]}")


def fit_and_eval(data: Path, run: Path, sets: list[str], eval_spp: int, what: str, extra: Sequence[str] = (),
                 eval_args: Sequence[str] = ()) -> None:
    """``nefii fit DATA --out RUN`` (resumed from its checkpoints if any; skipped if ``RUN/model.pt`` exists) with
    the arguments ``sets`` (``--set``s, ``--mesh`` or ``--geometry``), then ``nefii eval RUN`` with ``eval_args``
    (e.g. ``--data CLEAN``); nothing if ``RUN`` is already evaluated. ``RUN/benchmark.json`` records the code and
    the ``extra`` overrides. A failed fit or eval raises naming ``what`` with the end of its stderr."""
    if (run / "eval" / "metrics.json").exists():
        return
    if not (run / "model.pt").exists():
        (run / "benchmark.json").unlink(missing_ok=True)
        resume = ["--resume"] if (run / "checkpoints").exists() else []
        nefii("fit", str(data), "--out", str(run), "--quiet", *resume, *sets, what=f"fit {what}")
        (run / "benchmark.json").write_text(json.dumps({"code": code_version(), "extra": list(extra)}) + "\n")
    nefii("eval", str(run), *eval_args, "--spp", str(eval_spp), "--quiet", what=f"eval {what}")


def all_steps_wall_min(stats: dict) -> tuple[float, bool]:
    """Minutes for all of a run's steps, and whether it was resumed: a resumed run's stats time only its last
    session, which is scaled to all its steps (and marked)."""
    done = stats.get("steps_this_session", stats["steps"])
    wall = stats.get("wall_s_this_session", stats.get("wall_s")) * stats["steps"] / max(done, 1)
    return wall / 60, done < stats["steps"]


def run_figures(run: Path) -> dict | None:
    """An evaluated fit's figures, or None if ``run`` is not evaluated: the masked metrics, ``whole`` (the
    whole-image ones), ``fit_s`` (all its steps, :func:`all_steps_wall_min`), ``resumed``, ``peak_gib``,
    ``threads`` and ``code`` (from ``benchmark.json``, ``unknown`` without one)."""
    if not (run / "eval" / "metrics.json").exists():
        return None
    m = json.loads((run / "eval" / "metrics.json").read_text())
    stats = json.loads((run / "fit_stats.json").read_text())
    bench = json.loads((run / "benchmark.json").read_text()) if (run / "benchmark.json").exists() else {}
    wall_min, resumed = all_steps_wall_min(stats)
    return {"fit_s": wall_min * 60, "resumed": resumed, "peak_gib": stats["peak_rss_gib"],
            "threads": stats.get("threads"), "code": bench.get("code", "unknown"), **m["masked"],
            "whole": m["whole_image"]}


def fit_arguments(ap) -> None:
    """The scene size, eval and job options that the fit-and-score benchmarks share."""
    ap.add_argument("--res", type=int, default=128)
    ap.add_argument("--views", type=int, default=64)
    ap.add_argument("--test-views", type=int, default=8)
    ap.add_argument("--eval-spp", type=int, default=64)
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--threads", type=int, default=None, help="threads per fit (default: 1 with --jobs > 1, else all)")
    ap.add_argument("--set", dest="extra", action="append", default=[])


def note_lines(note: str) -> list[str]:
    """A results file's hand-written paragraph: ``note`` (``@FILE``: FILE's text) and a blank line; none if empty."""
    text = Path(note[1:]).read_text().strip() if note.startswith("@") else note.strip()
    return [text, ""] if text else []


def write_results(name: str, lines: list[str]) -> None:
    """Print a results table and write it to ``results/<name>`` (atomically)."""
    from nefii.io.atomic import write_text_atomic  # noqa: PLC0415

    text = "\n".join(lines) + "\n"
    print(text)
    RESULTS.mkdir(exist_ok=True)
    write_text_atomic(RESULTS / name, text)


def stamp() -> str:
    return time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())


def code_version() -> str:
    """The repository's HEAD commit (short), with ``+dirty`` if ``src/`` has uncommitted changes."""
    try:
        head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True,
                              check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--", "src"], cwd=REPO, capture_output=True,
                               text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"
    return head + ("+dirty" if dirty else "")
