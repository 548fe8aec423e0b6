"""Tests written to fail on bugs that once passed the whole suite (issue 26, item 7), each
checking a value against the same value computed another way:

* the material decode (albedo = sigmoid of output channels 0..2, roughness from channel 3);
* ``pair_distance`` under the ``log1p`` tone map (the slope enters squared);
* numbered checkpoints: the newest is found, killed writes are ignored, only ``keep`` are kept.

The per-view scoring of ``nefii eval`` is in ``test_catches_eval_per_view.py``. docs/testing.md
lists the seeded bugs and which test catches each.
"""
import math

import pytest
import torch

from nefii.fields.encodings import FourierFeatures, HashGrid
from nefii.fields.material import MaterialField
from nefii.fit.losses import distance, pair_distance, tonemap, tonemap_slope
from nefii.io.atomic import atomic_path
from nefii.io.checkpoints import latest_checkpoint, save_checkpoint

# ---------------------------------------------------------------------------- the material decode

LOGITS = torch.tensor([-1.3, 0.4, 2.1, -0.6])
"""four distinct output values of the material MLP's last layer"""


def _sigmoid(x: float) -> float:
    return 1.0 / (1.0 + math.exp(-x))


def _constant_output(field: MaterialField, values: torch.Tensor) -> None:
    """Make the field's MLP output ``values`` everywhere: zero weights, the values as bias."""
    last = field.net[-1]
    assert isinstance(last, torch.nn.Linear) and last.out_features == 4
    with torch.no_grad():
        last.weight.zero_()
        last.bias.copy_(values)


@pytest.mark.parametrize("encoding", ["hashgrid", "fourier"])
def test_material_decode_reads_albedo_from_channels_0_to_2_and_roughness_from_3(encoding):
    torch.manual_seed(0)
    enc = HashGrid(4, 2, 10, 4, 32, init_scale=3.0) if encoding == "hashgrid" else FourierFeatures(3, 4)
    field = MaterialField(enc, 16, 2, (torch.zeros(3), torch.ones(3)))
    _constant_output(field, LOGITS)
    mat = field(torch.rand(50, 3))
    want_albedo = torch.tensor([_sigmoid(float(v)) for v in LOGITS[:3]])
    want_rough = 0.911 * _sigmoid(float(LOGITS[3])) + 0.089
    assert mat.albedo.shape == (50, 3) and mat.roughness.shape == (50,)
    assert torch.allclose(mat.albedo, want_albedo.expand(50, 3), atol=1e-6)
    assert torch.allclose(mat.roughness, torch.full((50,), want_rough), atol=1e-6)
    # the override replaces the roughness only
    fixed = field(torch.rand(7, 3), roughness_override=0.5)
    assert torch.allclose(fixed.albedo, want_albedo.expand(7, 3), atol=1e-6)
    assert torch.equal(fixed.roughness, torch.full((7,), 0.5))


def test_material_decode_follows_each_output_channel_separately():
    """A last layer that copies one input feature into each channel with a different gain: each of
    albedo r, g, b and roughness must follow its own channel, point by point (batch shape kept)."""
    torch.manual_seed(1)
    field = MaterialField(FourierFeatures(3, 2), 8, 0, (torch.zeros(3), torch.ones(3)))   # layers=0: one Linear
    gains = torch.tensor([1.5, -2.0, 0.7, 3.0])
    with torch.no_grad():
        field.net[-1].weight.zero_()
        for c in range(4):
            field.net[-1].weight[c, c % 3] = gains[c]      # FourierFeatures' first 3 features are u itself
        field.net[-1].bias.copy_(LOGITS)
    x = torch.rand(4, 5, 3)                              # box [0, 1]^3: u = x
    mat = field(x)
    out = LOGITS + gains * x[..., [0, 1, 2, 0]]
    assert mat.albedo.shape == (4, 5, 3) and mat.roughness.shape == (4, 5)
    assert torch.allclose(mat.albedo, 1 / (1 + torch.exp(-out[..., :3])), atol=1e-6)
    assert torch.allclose(mat.roughness, 0.911 / (1 + torch.exp(-out[..., 3])) + 0.089, atol=1e-6)


def test_material_decode_maps_points_into_the_box():
    """u = (x - lo) / (hi - lo) is what the encoding sees: a field on box B at x equals one on [0,1]^3 at u."""
    torch.manual_seed(2)
    lo, hi = torch.tensor([-2.0, 1.0, 0.5]), torch.tensor([2.0, 3.0, 4.5])
    unit = MaterialField(FourierFeatures(3, 3), 8, 1, (torch.zeros(3), torch.ones(3)))
    boxed = MaterialField(FourierFeatures(3, 3), 8, 1, (lo, hi))
    boxed.load_state_dict(unit.state_dict() | {"box_lo": lo, "box_size": hi - lo})
    u = torch.rand(20, 3)
    a, b = unit(u), boxed(lo + u * (hi - lo))
    assert torch.allclose(a.albedo, b.albedo, atol=1e-5) and torch.allclose(a.roughness, b.roughness, atol=1e-5)


# ---------------------------------------------------------------------------- the pair loss under a tone map

def _random_pair(seed: int, shape=(64, 3)):
    g = torch.Generator().manual_seed(seed)
    t = torch.rand(shape, generator=g, dtype=torch.float64) * 4.0          # radiance up to 4: slopes 1 .. 0.2
    a = t + torch.randn(shape, generator=g, dtype=torch.float64) * 0.5
    b = t + torch.randn(shape, generator=g, dtype=torch.float64) * 0.5
    return a, b, t


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_pair_distance_log1p_is_the_closed_form_with_the_slope_squared(seed):
    a, b, t = _random_pair(seed)
    w = 1.0 / (1.0 + t)
    want = (w * w * (a - t) * (b - t)).mean()
    got = pair_distance(a, b, t, "log1p")
    assert torch.allclose(got, want, rtol=1e-12, atol=0), (float(got), float(want))
    # the linear case: no weights
    assert torch.allclose(pair_distance(a, b, t, "none"), ((a - t) * (b - t)).mean(), rtol=1e-12, atol=0)


def test_pair_distance_of_one_estimate_with_itself_is_the_tone_weighted_squared_error():
    a, _, t = _random_pair(3)
    w = 1.0 / (1.0 + t)
    want = ((w * (a - t)) ** 2).mean()
    assert torch.allclose(pair_distance(a, a, t, "log1p"), want, rtol=1e-12, atol=0)
    # ... which is, to first order, the squared error of the tone-mapped colours
    small = t + 1e-4 * torch.randn_like(t)
    first_order = (tonemap(small, "log1p") - tonemap(t, "log1p")).square().mean()
    assert float(pair_distance(small, small, t, "log1p")) == pytest.approx(float(first_order), rel=1e-3)
    assert float(distance(tonemap(small, "log1p"), tonemap(t, "log1p"), "l2")) == pytest.approx(
        float(first_order), rel=1e-12)


def test_pair_distance_weights_are_detached_and_clamped_at_zero_radiance():
    a, b, t = _random_pair(4, (10, 3))
    t = t - 1.0                                     # some negative targets: the slope there is 1 (clamped)
    t.requires_grad_(True)
    pair_distance(a, b, t, "log1p").backward()
    td = t.detach()
    w = 1.0 / (1.0 + td.clamp_min(0.0))
    # d/dt mean(w^2 (a - t)(b - t)) with w held constant
    want = -(w * w * ((b - td) + (a - td))) / td.numel()
    assert torch.allclose(t.grad, want, rtol=1e-10, atol=1e-14)


def test_tonemap_slope_is_the_derivative_of_the_tonemap():
    x = torch.tensor([0.0, 0.05, 0.5, 1.0, 3.0, 20.0], dtype=torch.float64)
    for kind in ("none", "log1p"):
        h = 1e-7
        fd = (tonemap(x + h, kind) - tonemap(x, kind)) / h              # forward difference: x = 0 is a kink
        assert torch.allclose(tonemap_slope(x, kind), fd, rtol=1e-5), kind
    assert torch.equal(tonemap_slope(torch.tensor([-3.0]), "log1p"), torch.tensor([1.0]))
    for f in (tonemap, tonemap_slope):
        with pytest.raises(ValueError, match="tonemap"):
            f(x, "gamma")


# ---------------------------------------------------------------------------- numbered checkpoints

def _state(step: int) -> dict:
    return {"step": step, "w": torch.full((2,), float(step))}


def test_latest_checkpoint_is_the_newest_of_three(tmp_path):
    assert latest_checkpoint(tmp_path) is None
    for step in (7, 40, 1200):                      # names of different digit counts
        save_checkpoint(tmp_path, step, _state(step), keep=3)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["step_0000007.pt", "step_0000040.pt", "step_0001200.pt"]
    latest = latest_checkpoint(tmp_path)
    assert latest == tmp_path / "step_0001200.pt"
    assert torch.load(latest)["step"] == 1200


def test_latest_checkpoint_ignores_and_removes_the_temporary_of_a_killed_write(tmp_path):
    for step in (10, 20):
        save_checkpoint(tmp_path, step, _state(step), keep=3)
    # a write of step 30 killed half way: its temporary (named as atomic_path names it) stays behind
    seen = []
    with pytest.raises(KeyboardInterrupt):
        with atomic_path(tmp_path / "step_0000030.pt") as tmp:
            seen.append(tmp)
            tmp.write_bytes(b"half a checkpoint")
            raise KeyboardInterrupt
    stale = seen[0]
    stale.write_bytes(b"half a checkpoint")         # what a SIGKILL (no cleanup) leaves
    assert stale.name.startswith(".step_0000030.") and stale.suffix == ".pt"
    assert latest_checkpoint(tmp_path) == tmp_path / "step_0000020.pt"
    assert not stale.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["step_0000010.pt", "step_0000020.pt"]


@pytest.mark.parametrize("keep", [1, 2, 3])
def test_save_checkpoint_keeps_only_the_newest(tmp_path, keep):
    steps = [3, 9, 10, 99, 100, 1000]
    for i, step in enumerate(steps):
        path = save_checkpoint(tmp_path, step, _state(step), keep=keep)
        assert path == tmp_path / f"step_{step:07d}.pt"
        kept = sorted(p.name for p in tmp_path.iterdir())
        assert kept == [f"step_{s:07d}.pt" for s in steps[max(0, i + 1 - keep):i + 1]], (keep, step, kept)
    assert latest_checkpoint(tmp_path) == tmp_path / "step_0001000.pt"
    assert torch.load(latest_checkpoint(tmp_path))["w"].tolist() == [1000.0, 1000.0]


def test_save_checkpoint_default_keeps_two(tmp_path):
    for step in (1, 2, 3):
        save_checkpoint(tmp_path, step, _state(step))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["step_0000002.pt", "step_0000003.pt"]
