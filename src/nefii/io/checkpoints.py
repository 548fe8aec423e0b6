"""Numbered training checkpoints, written atomically, the newest kept; resume reads the newest that loads.

Names are ``step_XXXXXXX.pt`` (at least 7 digits) and are ordered by the parsed step, not as text, so step
10,000,000 comes after step 9,999,999. A write killed half way leaves only a temporary (``.step_*``), which
is ignored and removed; a checkpoint that is truncated or empty all the same (a disk that filled up, a copy
cut short) is skipped for the one before it. A checkpoint that asks to run code is refused outright.
"""
from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import torch

from ..errors import InputError
from .atomic import atomic_path
from .safe_load import UnsafeFileError, load_tensors

_NAME = re.compile(r"step_(\d+)\.pt")


def checkpoint_step(path: Path) -> int | None:
    """The step in a checkpoint's name, or None for any other file."""
    m = _NAME.fullmatch(path.name)
    return int(m.group(1)) if m else None


def list_checkpoints(folder: Path) -> list[Path]:
    """The checkpoints in ``folder``, oldest first (by step)."""
    if not folder.is_dir():
        return []
    found = [(checkpoint_step(p), p) for p in folder.iterdir() if p.is_file()]
    return [p for step, p in sorted((s, p) for s, p in found if s is not None)]


def save_checkpoint(folder: Path, step: int, state: dict, keep: int = 2) -> Path:
    """Write ``state`` as ``folder/step_XXXXXXX.pt`` atomically; keep the newest ``keep``."""
    path = folder / f"step_{step:07d}.pt"
    with atomic_path(path) as tmp:
        torch.save(state, tmp)
    for old in list_checkpoints(folder)[:-keep]:
        old.unlink()
    return path


def remove_temporaries(folder: Path) -> None:
    """Remove the temporaries of checkpoint writes that were killed."""
    if folder.is_dir():
        for stale in folder.glob(".step_*"):
            stale.unlink(missing_ok=True)


def latest_checkpoint(folder: Path) -> Path | None:
    """The newest complete checkpoint by step; temporaries of a write that was killed are removed."""
    remove_temporaries(folder)
    found = list_checkpoints(folder)
    return found[-1] if found else None


@dataclass(frozen=True)
class LoadedCheckpoint:
    path: Path
    state: dict[str, Any]
    """what the trainer's ``state_dict`` returned, tensors on the CPU"""

    @property
    def step(self) -> int:
        return int(self.state["step"])

    def restore(self, load_state_dict: Callable[[dict[str, Any]], None], what: str) -> None:
        """``load_state_dict(self.state)``; a state that does not fit (other shapes, missing keys) is an
        :class:`InputError` naming this file: ``does not fit WHAT (...)``."""
        try:
            load_state_dict(self.state)
        except (KeyError, RuntimeError, TypeError, ValueError) as e:
            raise InputError(self.path, f"does not fit {what} ({type(e).__name__}: "
                                        f"{str(e).splitlines()[0][:160]})") from None


def load_latest_checkpoint(folder: Path, warn: Callable[[str], None] = lambda s: None) -> LoadedCheckpoint | None:
    """The newest checkpoint that loads, and its state; None when there is none. Each newer one that does not
    load (truncated, empty, not a nefii checkpoint) is passed over with one line to ``warn``; one that asks to
    run code raises :class:`UnsafeFileError`."""
    remove_temporaries(folder)
    for path in reversed(list_checkpoints(folder)):
        try:
            state = load_tensors(path, "cpu")
            if "step" not in state:
                raise InputError(path, "not a nefii checkpoint (no 'step')")
        except UnsafeFileError:
            raise
        except InputError as e:
            warn(f"skipping {e}")
            continue
        return LoadedCheckpoint(path, state)
    return None
