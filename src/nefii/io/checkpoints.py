"""Numbered training checkpoints, written atomically, the last two kept."""
from __future__ import annotations

from pathlib import Path

import torch

from .atomic import atomic_path


def save_checkpoint(folder: Path, step: int, state: dict, keep: int = 2) -> Path:
    """Write ``state`` as ``folder/step_XXXXXXX.pt`` atomically; keep the newest ``keep``."""
    path = folder / f"step_{step:07d}.pt"
    with atomic_path(path) as tmp:
        torch.save(state, tmp)
    for old in sorted(folder.glob("step_*.pt"))[:-keep]:
        old.unlink()
    return path


def latest_checkpoint(folder: Path) -> Path | None:
    """The newest complete checkpoint; temporaries of a write that was killed are removed."""
    for stale in folder.glob(".step_*"):
        stale.unlink(missing_ok=True)
    found = sorted(folder.glob("step_*.pt"))
    return found[-1] if found else None
