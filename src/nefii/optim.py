"""One optimiser step, as the geometry stage and the refinement take it."""
from __future__ import annotations

import torch
from torch import Tensor


def descend(loss: Tensor, optimizer: torch.optim.Optimizer, scheduler: torch.optim.lr_scheduler.LRScheduler,
            what: str) -> None:
    """``loss`` backpropagated, then one step of ``optimizer`` and of its ``scheduler``; a loss that is not finite
    raises :class:`FloatingPointError` naming ``what`` (e.g. ``"step 12: geometry loss"``) before anything moves."""
    if not bool(torch.isfinite(loss)):
        raise FloatingPointError(f"{what} is not finite ({loss.item()})")
    optimizer.zero_grad(set_to_none=True)
    loss.backward()
    optimizer.step()
    scheduler.step()
