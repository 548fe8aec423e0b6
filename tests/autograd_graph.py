"""What a tensor was computed through, for tests that check which of two code paths ran."""
from __future__ import annotations

import torch


def graph_names(t: torch.Tensor) -> set[str]:
    """Names of the autograd nodes that ``t`` was computed through."""
    names, todo = set(), [t.grad_fn]
    while todo:
        node = todo.pop()
        if node is not None and type(node).__name__ not in names:
            names.add(type(node).__name__)
            todo.extend(f for f, _ in node.next_functions)
    return names
