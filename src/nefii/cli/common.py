"""Small helpers the verbs share: devices, threads, the rendering flags of eval and relight checked like a
config (:func:`nefii.config_tools.validate`), all before any data is read."""
from __future__ import annotations

import argparse
import os
from dataclasses import dataclass
from typing import Annotated

import torch

from ..config_tools import Range, validate
from ..errors import InputError


def pick_device(name: str) -> torch.device:
    """``auto`` is CUDA when present, else the CPU; a name that is not ``cpu``, ``cuda`` or ``cuda:N``, or
    CUDA without one, is an input error."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        device = torch.device(name)
    except (RuntimeError, ValueError):
        device = None
    if device is None or device.type not in ("cpu", "cuda"):
        raise InputError(None, f"--device {name}: not a device (use cpu, cuda, cuda:N or auto)")
    if device.type == "cuda":
        if not torch.cuda.is_available():
            raise InputError(None, f"--device {name}: no CUDA device is available")
        if device.index is not None and device.index >= torch.cuda.device_count():
            raise InputError(None, f"--device {name}: there are {torch.cuda.device_count()} CUDA device(s)")
    return device


@dataclass(frozen=True)
class RenderFlags:
    """The numbers eval and relight take on the command line, with their ranges."""

    spp: Annotated[int, Range(1, 1 << 16)]
    """estimator samples (eval) or paths (relight) per pixel"""
    seed: Annotated[int, Range(0, 2**63 - 1)]
    """seeds the samples"""
    max_bounces: Annotated[int, Range(1, 1024)] = 8
    """relight: surface interactions per path"""
    threads: Annotated[int, Range(0, 4096)] = 0
    """CPU threads (0: the cores this process may use)"""


def render_flags(args: argparse.Namespace) -> RenderFlags:
    """``--spp``, ``--seed`` (and ``--max-bounces``, ``--threads``) checked; a bad one is an input error naming
    the flag."""
    threads = getattr(args, "threads", None)
    flags = RenderFlags(args.spp, args.seed, getattr(args, "max_bounces", 8), 0 if threads is None else threads)
    try:
        validate(flags)
    except ValueError as e:
        name, problem = str(e).split(": ", 1)
        raise InputError(None, f"--{name.replace('_', '-')}: {problem}") from None
    return flags


def add_threads_flag(p: argparse.ArgumentParser) -> None:
    """``--threads N`` for a verb that renders a fitted run (default: the threads the run was fitted with)."""
    p.add_argument("--threads", type=int, default=None,
                   help="CPU threads (0: all cores this process may use; default: the fit's setting)")


def set_threads(threads: int) -> int:
    """Use ``threads`` CPU threads (0: the cores this process may run on); returns the number set."""
    n = threads or len(os.sched_getaffinity(0))
    torch.set_num_threads(n)
    return n
