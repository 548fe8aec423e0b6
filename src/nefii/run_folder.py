"""Run folders that protect themselves: what ``nefii fit`` and ``nefii geometry`` may write into.

    RUN/run.json   the manifest: the kind of run (``fit`` or ``geometry``) and the data it was fitted on
                   (:class:`nefii.data.fingerprint.DataFingerprint`), written before the first checkpoint
    RUN/run.lock   held while a process writes the folder (:mod:`nefii.io.lock`)

A run writes only into a folder that is absent, empty, or a nefii run of the same kind (one with a
``run.json``); a fresh run only where no checkpoint and no result is there yet, so a run that failed before
its first checkpoint can simply be started again; ``--resume`` only on the data in the manifest.
"""
from __future__ import annotations

import json
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterator

from .data.fingerprint import DataFingerprint
from .errors import InputError
from .io.atomic import write_text_atomic
from .io.checkpoints import LoadedCheckpoint, latest_checkpoint, list_checkpoints, load_latest_checkpoint
from .io.lock import LOCK_FILE, RunLock

MANIFEST_FILE = "run.json"
KINDS = {"fit": "model.pt", "geometry": "sdf.pt"}
"""each kind of run and the result file a finished one holds"""


@dataclass(frozen=True)
class RunManifest:
    kind: str
    """``fit`` or ``geometry``"""
    data: DataFingerprint | None = None
    """what the run is fitted on (None until the data has been read)"""


def read_manifest(folder: Path) -> RunManifest | None:
    """The folder's manifest; None when it has none."""
    path = folder / MANIFEST_FILE
    if not path.is_file():
        return None
    try:
        d = json.loads(path.read_text())
        kind = d["kind"]
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise InputError(path, f"not a readable run manifest ({type(e).__name__})") from None
    if kind not in KINDS:
        raise InputError(path, f"unknown kind of run {kind!r}")
    data = None if d.get("data") is None else DataFingerprint.from_dict(d["data"], path)
    return RunManifest(kind, data)


def write_manifest(folder: Path, manifest: RunManifest) -> None:
    d = {"kind": manifest.kind, "data": None if manifest.data is None else manifest.data.to_dict()}
    write_text_atomic(folder / MANIFEST_FILE, json.dumps(d, indent=2) + "\n")


def has_progress(folder: Path, kind: str) -> bool:
    """The run got somewhere: a checkpoint or its result exists."""
    return bool(list_checkpoints(folder / "checkpoints")) or (folder / KINDS[kind]).exists()


def claim(folder: Path, kind: str, resume: bool) -> RunManifest | None:
    """The manifest of the run ``folder`` holds (None: the folder is empty); refuses a folder that is not a
    nefii run of ``kind``, and, without ``resume``, one whose run has a checkpoint or a result."""
    others = [p for p in folder.iterdir() if p.name != LOCK_FILE] if folder.is_dir() else []
    if not others:
        return None
    manifest = read_manifest(folder)
    if manifest is None:
        raise InputError(folder, f"is neither empty nor a nefii {kind} run folder (no {MANIFEST_FILE}); nefii will "
                                 "not write into it: choose another --out")
    if manifest.kind != kind:
        raise InputError(folder, f"holds a nefii {manifest.kind} run, not a {kind} run: choose another --out")
    if not resume and has_progress(folder, kind):
        what = "a run" if kind == "fit" else f"a {kind} run"
        raise InputError(folder, f"already holds {what}: use --resume to continue it, or another --out")
    return manifest


@contextmanager
def writing_run(folder: Path, kind: str, resume: bool,
                warn: Callable[[str], None] = lambda s: None) -> Iterator[RunManifest | None]:
    """Hold ``folder``'s lock while the body writes the run; yields :func:`claim`'s manifest. A folder this
    call created is removed again if nothing was written into it (bad input found later)."""
    if folder.exists() and not folder.is_dir():
        raise InputError(folder, "exists and is not a folder: --out wants a folder")
    created = not folder.exists()
    lock = RunLock(folder, kind)
    try:
        lock.acquire(warn)
    except OSError as e:
        raise InputError(folder, f"cannot be created or written ({e.strerror})") from None
    try:
        yield claim(folder, kind, resume)
    finally:
        lock.release()
        if created and folder.is_dir() and not any(folder.iterdir()):
            folder.rmdir()


def _label(kind: str) -> str:
    return "run" if kind == "fit" else f"{kind} run"


def resume_point(folder: Path, kind: str, manifest: RunManifest | None, warn: Callable[[str], None],
                 say: Callable[[str], None]) -> LoadedCheckpoint | None:
    """What ``--resume`` continues from: the newest checkpoint of ``folder`` that loads (each newer one that
    does not is passed to ``warn``), or None, said, for a run that failed before its first checkpoint. A
    folder holding no run (``manifest`` None), or checkpoints none of which loads, is an :class:`InputError`."""
    if manifest is None:
        raise InputError(folder, f"no {_label(kind)} to resume here")
    ckpt = folder / "checkpoints"
    found = load_latest_checkpoint(ckpt, warn=warn)
    if found is None:
        if list_checkpoints(ckpt):
            raise InputError(ckpt, "no checkpoint in it loads (all truncated or corrupt): start a new run")
        say("the run wrote no checkpoint before it stopped: starting from the first step")
    return found


def after_failure(folder: Path) -> str:
    """What a run that stopped on an error can do next: resume from its last good checkpoint, or start over."""
    last = latest_checkpoint(folder / "checkpoints")
    return (f"the last good checkpoint is {last} (--resume continues from it)" if last is not None else
            "no checkpoint was written: run the same command again to start over")
