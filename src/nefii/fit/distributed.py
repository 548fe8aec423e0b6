"""Data parallel training over processes (``torchrun``): gloo on the CPU, nccl on CUDA.

Every process holds the whole model and draws its own pixel batches (its generator is seeded
with ``seed + 1000 * rank``); after each backward pass the gradients are averaged across
processes, so every process takes the same optimiser step and the replicas stay identical.
Rank 0 alone writes checkpoints, logs and outputs. Started without ``torchrun`` (no
``WORLD_SIZE`` in the environment) it is a single process and all of this is a no-op.
"""
from __future__ import annotations

import os
from dataclasses import dataclass

import torch
import torch.distributed as dist
from torch import Tensor

from ..errors import InputError


@dataclass(frozen=True)
class DistContext:
    rank: int = 0
    world_size: int = 1

    @property
    def active(self) -> bool:
        return self.world_size > 1

    @property
    def is_main(self) -> bool:
        return self.rank == 0


def init_distributed(device: torch.device) -> DistContext:
    """Join the process group ``torchrun`` set up, if any."""
    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world <= 1:
        return DistContext()
    if not dist.is_initialized():
        dist.init_process_group(backend="nccl" if device.type == "cuda" else "gloo")
    return DistContext(rank=dist.get_rank(), world_size=dist.get_world_size())


def local_device(device: torch.device, ctx: DistContext) -> torch.device:
    """On CUDA each process takes the GPU of its local rank; NCCL refuses two processes on one GPU."""
    if device.type == "cuda" and ctx.active:
        per_node, gpus = int(os.environ.get("LOCAL_WORLD_SIZE", ctx.world_size)), torch.cuda.device_count()
        if per_node > gpus:
            raise InputError(None, f"{per_node} processes per node but {gpus} CUDA device(s): start at most one "
                                   "process per GPU, or use --device cpu")
        return torch.device("cuda", int(os.environ.get("LOCAL_RANK", ctx.rank)))
    return device


def all_mean(tensors: list[Tensor], ctx: DistContext) -> list[Tensor]:
    """The mean of each tensor over every process (one flat all-reduce; a collective). Alone: ``tensors``."""
    if not ctx.active:
        return tensors
    flat = torch.cat([t.reshape(-1) for t in tensors])
    dist.all_reduce(flat)
    flat /= ctx.world_size
    return list(torch.split(flat, [t.numel() for t in tensors]))


def average_gradients(params: list[torch.nn.Parameter], ctx: DistContext) -> None:
    """All-reduce the gradients of ``params`` (one flat buffer) and divide by the world size."""
    if not ctx.active:
        return
    grads = [p.grad if p.grad is not None else torch.zeros_like(p) for p in params]
    for p, g in zip(params, all_mean(grads, ctx)):
        p.grad = g.view_as(p)


def any_rank(flag: bool, ctx: DistContext, device: torch.device) -> bool:
    """True if ``flag`` is true on any process (a collective: every process must call it)."""
    if not ctx.active:
        return flag
    t = torch.tensor([1.0 if flag else 0.0], device=device)
    dist.all_reduce(t, op=dist.ReduceOp.MAX)
    return bool(t.item() > 0)


def parameter_checksums(model: torch.nn.Module, ctx: DistContext, device: torch.device) -> list[float]:
    """Sum of all parameters on every process (gathered to all): equal when the replicas are in sync."""
    s = torch.tensor([sum(float(p.detach().double().sum()) for p in model.parameters())], device=device,
                     dtype=torch.float64)
    if not ctx.active:
        return [float(s)]
    out = [torch.zeros_like(s) for _ in range(ctx.world_size)]
    dist.all_gather(out, s)
    return [float(t) for t in out]


def shutdown(ctx: DistContext, clean: bool) -> None:
    """Leave the process group. After a ``clean`` run every process first waits for the others (a barrier), so
    none tears down its connections and exits while another still holds them (rank 0 writes the outputs after
    the other ranks are done); after a failure it leaves at once, and ``torchrun`` stops the others."""
    if ctx.active and dist.is_initialized():
        if clean:
            dist.barrier()
        dist.destroy_process_group()
