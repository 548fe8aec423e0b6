"""Small helpers the verbs share: devices, threads, config errors as InputErrors."""
from __future__ import annotations

import os

import torch

from ..errors import InputError


def pick_device(name: str) -> torch.device:
    """``auto`` is CUDA when present, else the CPU; asking for CUDA without one is an input error."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name.startswith("cuda") and not torch.cuda.is_available():
        raise InputError(None, f"--device {name}: no CUDA device is available")
    return torch.device(name)


def set_threads(threads: int) -> int:
    """Use ``threads`` CPU threads (0: the cores this process may run on); returns the number set."""
    n = threads or len(os.sched_getaffinity(0))
    torch.set_num_threads(n)
    return n
