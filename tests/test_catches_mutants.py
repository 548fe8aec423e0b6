"""Tests that kill mutants which survived ``make mutants`` (docs/testing.md lists them and the mutants
left alive as equivalent). Each checks a value against one computed another way."""
from dataclasses import fields
from types import SimpleNamespace

import pytest
import torch

from nefii.fit.losses import SecondaryHitBuffer, distance, pair_distance, render_distance
from nefii.fit import losses
from nefii.io.checkpoints import latest_checkpoint, save_checkpoint

SurfacePoints = losses.SurfacePoints
"""the points type the buffer stores (wherever the fit package defines it)"""


def _random_pair(seed: int, shape=(64, 3)):
    g = torch.Generator().manual_seed(seed)
    t = torch.rand(shape, generator=g, dtype=torch.float64) * 4.0
    a = t + torch.randn(shape, generator=g, dtype=torch.float64) * 0.5
    b = t + torch.randn(shape, generator=g, dtype=torch.float64) * 0.5
    return a, b, t


def _state(step: int) -> dict:
    return {"step": step, "w": torch.full((2,), float(step))}


# ---------------------------------------------------------------------------- fit/losses.py

def test_distance_kinds_are_their_closed_forms():
    a, b, _ = _random_pair(5)
    assert torch.allclose(distance(a, b, "l1"), (a - b).abs().mean(), rtol=1e-12, atol=0)
    assert torch.allclose(distance(a, b, "l2"), ((a - b) ** 2).mean(), rtol=1e-12, atol=0)
    assert torch.equal(distance(a, b, "l2_pair"), distance(a, b, "l2"))     # one estimate: plain l2
    with pytest.raises(ValueError, match=r"unknown loss 'huber' \(l1 \| l2 \| l2_pair\)"):
        distance(a, b, "huber")


def _traced(rgb, pair=None):
    """What render_distance reads of a path-traced result: ``radiance.rgb`` and the two half estimates."""
    return SimpleNamespace(radiance=SimpleNamespace(rgb=rgb),
                           pair=None if pair is None else tuple(SimpleNamespace(rgb=p) for p in pair))


def test_render_distance_tone_maps_both_sides_or_uses_the_pair():
    a, b, t = _random_pair(6)
    full = (a + b) / 2
    traced = _traced(full, (a, b))
    for kind in ("l1", "l2"):
        want = distance(torch.log1p(full.clamp_min(0)), torch.log1p(t), kind)
        assert torch.allclose(render_distance(traced, t, "log1p", kind), want, rtol=1e-12, atol=0), kind
        assert torch.allclose(render_distance(traced, t, "none", kind), distance(full, t, kind), rtol=1e-12, atol=0)
    w = 1.0 / (1.0 + t)
    want = (w * w * (a - t) * (b - t)).mean()
    assert torch.allclose(render_distance(traced, t, "log1p", "l2_pair"), want, rtol=1e-12, atol=0)
    with pytest.raises(ValueError, match=r"^loss l2_pair needs num_samples >= 2 \(two independent half estimates\)$"):
        render_distance(_traced(full), t, "log1p", "l2_pair")




def _points(values) -> "SurfacePoints":
    """Points whose every field, in every component, holds ``values`` (one per point): easy to follow."""
    col = torch.as_tensor(values, dtype=torch.float32).unsqueeze(-1).repeat(1, 3)
    return SurfacePoints(*(col.clone() + i for i, _ in enumerate(fields(SurfacePoints))))


def test_secondary_buffer_starts_its_ring_at_slot_zero_and_keeps_the_newest_of_a_large_batch():
    buf = SecondaryHitBuffer(capacity=4)
    buf.add(_points([]))                                 # nothing added: still empty, nothing allocated
    assert len(buf) == 0 and buf.state_dict() is None
    buf.add(_points([7.0]))
    state = buf.state_dict()
    assert state["next"] == 1 and state["size"] == 1
    assert state["items"]["position"][0].tolist() == [7.0] * 3   # the first point goes into slot 0
    buf.add(_points([10.0, 11, 12, 13, 14, 15]))         # more than the capacity at once: the last 4
    state = buf.state_dict()
    assert len(buf) == 4 and state["size"] == 4 and state["next"] == 1
    assert sorted(state["items"]["position"][:, 0].tolist()) == [12.0, 13.0, 14.0, 15.0]
    for i, f in enumerate(fields(SurfacePoints)):        # every field travels with its point
        assert torch.equal(state["items"][f.name], state["items"]["position"] + i), f.name


def test_secondary_buffer_samples_reproducibly_from_its_generator_and_not_from_an_empty_buffer():
    buf = SecondaryHitBuffer(capacity=8)
    with pytest.raises(AssertionError, match=r"^sample\(\) from an empty buffer$"):
        buf.sample(3, torch.Generator().manual_seed(0))
    buf.add(_points([5.0]))
    one = buf.sample(4, torch.Generator().manual_seed(0))   # a buffer of one point can be sampled
    assert one.position[:, 0].tolist() == [5.0] * 4
    buf.add(_points([float(v) for v in range(6)]))
    draw = lambda seed: buf.sample(50, torch.Generator().manual_seed(seed)).position[:, 0]
    torch.manual_seed(123)
    a = draw(1)
    torch.manual_seed(456)                                   # the global generator plays no part
    assert torch.equal(a, draw(1))
    assert not torch.equal(a, draw(2))


def test_secondary_buffer_state_round_trips():
    buf = SecondaryHitBuffer(capacity=5)
    buf.add(_points([1.0, 2.0, 3.0]))
    buf.add(_points([4.0, 5.0, 6.0]))
    state = buf.state_dict()
    other = SecondaryHitBuffer(capacity=5)
    other.load_state_dict(state, torch.device("cpu"))
    assert len(other) == len(buf) == 5
    assert other.state_dict()["next"] == state["next"] == 1
    for name, t in state["items"].items():
        assert torch.equal(other.state_dict()["items"][name], t), name
    g = lambda: torch.Generator().manual_seed(3)
    assert torch.equal(other.sample(20, g()).position, buf.sample(20, g()).position)
    # checkpoints from before lookup normals: the shading normal stands in
    old = {k: v for k, v in state.items()} | {"items": {k: v for k, v in state["items"].items() if k != "lookup_normal"}}
    other.load_state_dict(old, torch.device("cpu"))
    assert torch.equal(other.state_dict()["items"]["lookup_normal"], state["items"]["normal"])
    other.load_state_dict(None, torch.device("cpu"))
    assert len(other) == 0 and other.state_dict() is None
    other.add(_points([9.0]))                                # and it starts again at slot 0
    assert other.state_dict()["items"]["position"][0, 0] == 9.0 and other.state_dict()["next"] == 1


# ---------------------------------------------------------------------------- io/checkpoints.py

def test_latest_checkpoint_tolerates_a_temporary_that_vanishes_while_it_cleans(tmp_path, monkeypatch):
    """Between listing a stale temporary and removing it, a concurrent writer may rename it onto its
    checkpoint: that is not an error."""
    save_checkpoint(tmp_path, 5, _state(5))
    ghost = tmp_path / ".step_0000006.gone.pt"                # listed, but no longer there
    real_glob = type(tmp_path).glob

    def glob(self, pattern, *args, **kwargs):
        found = list(real_glob(self, pattern, *args, **kwargs))
        return found + [ghost] if pattern.startswith(".step_") else found

    monkeypatch.setattr(type(tmp_path), "glob", glob)
    assert latest_checkpoint(tmp_path) == tmp_path / "step_0000005.pt"
