"""Tests that kill mutants which survived ``make mutants`` (docs/testing.md lists them and the mutants
left alive as equivalent). Each checks a value against one computed another way."""
from dataclasses import fields
from types import SimpleNamespace

import math

import numpy as np
import pytest
import torch
from skimage.metrics import structural_similarity

from nefii.evaluate.metrics import SSIM_PAD, median_scale, ssim
from nefii.evaluate.table1 import METRIC_KEYS, ViewArrays, mean_scores, view_scores
from nefii.fields.encodings import FourierFeatures, HashGrid
from nefii.fields.material import MaterialField
from nefii.fields.mlp import mlp
from nefii.render.brdf import F_schlick
from nefii.render.envmap import envmap_lookup
from nefii.fit.losses import SecondaryHitBuffer, distance, render_distance
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
    with pytest.raises(RuntimeError, match=r"^SecondaryHitBuffer.sample\(\) before any secondary hit was added"):
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


# ---------------------------------------------------------------------------- evaluate/metrics.py

def _ssim_map(a, b):
    """skimage's Gaussian SSIM map in float64 (the NeRF convention), channel-averaged."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    mean, smap = structural_similarity(a, b, gaussian_weights=True, sigma=1.5, use_sample_covariance=False,
                                       data_range=1.0, channel_axis=-1 if a.ndim == 3 else None, full=True)
    return mean, (smap.mean(-1) if smap.ndim == 3 else smap)


@pytest.mark.parametrize("channels", [None, 3])
def test_masked_ssim_is_the_map_mean_over_the_mask_inside_the_border(channels):
    rng = np.random.default_rng(7)
    shape = (24, 20) if channels is None else (24, 20, channels)
    a = rng.uniform(size=shape)
    b = np.clip(a + rng.normal(0, 0.1, shape), 0, 1)
    mask = np.zeros(shape[:2], bool)
    mask[2:15, 3:18] = True                                  # reaches into the border on two sides
    mean, smap = _ssim_map(a, b)
    assert ssim(a, b) == pytest.approx(mean, abs=1e-12)
    inner = np.zeros_like(mask)
    inner[SSIM_PAD:shape[0] - SSIM_PAD, SSIM_PAD:shape[1] - SSIM_PAD] = True
    want = smap[mask & inner].mean()
    assert ssim(a, b, mask) == pytest.approx(want, abs=1e-12)
    assert abs(want - smap[mask].mean()) > 1e-4 and abs(want - mean) > 1e-4   # the border and the mask matter
    border_only = np.zeros_like(mask)
    border_only[:SSIM_PAD] = True
    assert math.isnan(ssim(a, b, border_only))


def test_ssim_scores_in_float64_whatever_the_input_type():
    rng = np.random.default_rng(8)
    a = rng.uniform(size=(16, 16, 3)).astype(np.float32)
    b = np.clip(a + rng.normal(0, 0.05, a.shape), 0, 1).astype(np.float32)
    assert ssim(a, b) == pytest.approx(_ssim_map(a, b)[0], abs=1e-12)
    assert ssim(a, b) != structural_similarity(a, b, gaussian_weights=True, sigma=1.5, use_sample_covariance=False,
                                                data_range=1.0, channel_axis=-1)   # float32 arithmetic differs


def test_median_scale_is_float32_per_channel_and_one_for_an_empty_mask():
    rng = np.random.default_rng(9)
    pred = rng.uniform(0.1, 1, (5, 7, 3)).astype(np.float32)
    gt = pred * np.array([2.0, 3.0, 0.5], np.float32)
    full = np.ones((5, 7), bool)
    s = median_scale(pred, gt, full)
    assert s.dtype == np.float32 and s.shape == (3,) and np.allclose(s, [2.0, 3.0, 0.5], rtol=1e-6)
    empty = median_scale(pred, gt, np.zeros((5, 7), bool))
    assert empty.dtype == np.float32 and empty.tolist() == [1.0, 1.0, 1.0]
    assert median_scale(pred[..., :2], gt[..., :2], np.zeros((5, 7), bool)).tolist() == [1.0, 1.0]


# ---------------------------------------------------------------------------- evaluate/table1.py

def _srgb(x):
    x = np.clip(np.asarray(x, np.float64), 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * x ** (1 / 2.4) - 0.055)


def _psnr(a, b):
    return -10.0 * math.log10(float(np.mean((np.asarray(a, np.float64) - b) ** 2)))


def test_view_scores_are_table_1_by_hand_in_both_protocols():
    rng = np.random.default_rng(11)
    H = W = 24
    mask = np.zeros((H, W), bool)
    mask[3:19, 5:14] = True                  # inside the border on some sides only
    gt = ViewArrays(rgb=rng.uniform(size=(H, W, 3)), albedo=rng.uniform(0.1, 0.9, (H, W, 3)),
                    roughness=rng.uniform(size=(H, W)), specular=rng.uniform(size=(H, W, 3)) * 0.3)
    pred = ViewArrays(rgb=np.clip(gt.rgb + rng.normal(0, 0.05, (H, W, 3)), 0, None),
                      albedo=rng.uniform(0.1, 0.9, (H, W, 3)).astype(np.float32), roughness=rng.uniform(size=(H, W)),
                      specular=gt.specular * 1.2)
    blocks, scale = view_scores(pred, gt, mask)
    want_scale = np.median(gt.albedo[mask] / pred.albedo[mask], axis=0)
    assert scale.dtype == np.float32 and np.allclose(scale, want_scale, rtol=1e-6)
    white = lambda img: np.where(mask[..., None] if img.ndim == 3 else mask, img, 1.0)
    for name, p, g in (("albedo", pred.albedo * scale, gt.albedo), ("rgb", pred.rgb, gt.rgb),
                       ("specular", pred.specular, gt.specular)):
        ps, gs = _srgb(p), _srgb(g)
        _, smap = _ssim_map(ps, gs)
        inner = np.zeros_like(mask)
        inner[SSIM_PAD:-SSIM_PAD, SSIM_PAD:-SSIM_PAD] = True
        assert blocks["masked"][f"{name}_psnr"] == pytest.approx(_psnr(ps[mask], gs[mask]), rel=1e-5), name
        assert blocks["masked"][f"{name}_ssim"] == pytest.approx(smap[mask & inner].mean(), abs=1e-5), name
        assert blocks["whole_image"][f"{name}_psnr"] == pytest.approx(_psnr(white(ps), white(gs)), rel=1e-5), name
        assert blocks["whole_image"][f"{name}_ssim"] == pytest.approx(_ssim_map(white(ps), white(gs))[0], abs=1e-5)
    assert blocks["masked"]["roughness_mse"] == pytest.approx(np.mean((pred.roughness - gt.roughness)[mask] ** 2))
    assert blocks["whole_image"]["roughness_mse"] == pytest.approx(
        np.mean((white(pred.roughness) - white(gt.roughness)) ** 2))


def test_view_scores_leave_out_what_either_side_lacks():
    """Real photographs have no ground-truth albedo, roughness or specular: those columns are None (and
    the albedo scale 1), whichever side lacks the map, and the means skip them."""
    rng = np.random.default_rng(12)
    H = W = 16
    mask = np.ones((H, W), bool)
    full = ViewArrays(rgb=rng.uniform(size=(H, W, 3)), albedo=rng.uniform(0.1, 1, (H, W, 3)),
                      roughness=rng.uniform(size=(H, W)), specular=rng.uniform(size=(H, W, 3)))
    bare = ViewArrays(rgb=full.rgb, albedo=None, roughness=None, specular=None)
    for pred, gt in ((full, bare), (bare, full)):
        blocks, scale = view_scores(pred, gt, mask)
        assert scale.dtype == np.float32 and scale.tolist() == [1.0, 1.0, 1.0]
        for protocol in ("masked", "whole_image"):
            assert set(blocks[protocol]) == set(METRIC_KEYS)
            for k in METRIC_KEYS:
                assert (blocks[protocol][k] is None) == (not k.startswith("rgb") or k.endswith("lpips")), (k, blocks)
        means = mean_scores([blocks, blocks])
        assert means["masked"]["albedo_psnr"] is None and means["whole_image"]["specular_ssim"] is None
        assert means["masked"]["rgb_psnr"] == pytest.approx(blocks["masked"]["rgb_psnr"])


# ---------------------------------------------------------------------------- fields/

PRIMES = (1, 2654435761, 805459861)
"""the spatial hash of Mueller et al. 2022 (instant-NGP)"""


def _hashgrid_reference(table: np.ndarray, res: list[int], dense: list[bool], table_size: int, x: np.ndarray):
    """The encoding by its definition, one point, level and corner at a time: per level, the cell
    ``p0 = min(floor(x r), r - 1)``, its 8 corners' features (dense index ``x + (r+1)(y + (r+1) z)`` or the
    hash ``(x * 1 ^ y * 2654435761 ^ z * 805459861) mod T``) weighted trilinearly; levels concatenated."""
    out = np.zeros((len(x), len(res), table.shape[1]))
    offset = 0
    for level, r in enumerate(res):
        for i, p in enumerate(x):
            pos = np.clip(p, 0, 1) * r
            p0 = np.minimum(np.floor(pos), r - 1)
            f = pos - p0
            for dz in (0, 1):
                for dy in (0, 1):
                    for dx in (0, 1):
                        cx, cy, cz = (int(v) for v in p0 + (dx, dy, dz))
                        k = cx + (r + 1) * (cy + (r + 1) * cz) if dense[level] else \
                            ((cx * PRIMES[0]) ^ (cy * PRIMES[1]) ^ (cz * PRIMES[2])) % table_size
                        w = (f[0] if dx else 1 - f[0]) * (f[1] if dy else 1 - f[1]) * (f[2] if dz else 1 - f[2])
                        out[i, level] += w * table[offset + k]
        offset += (r + 1) ** 3 if dense[level] else table_size
    return out.reshape(len(x), -1)


def test_hashgrid_is_its_definition_with_the_instant_ngp_hash():
    """Resolutions 3, 6, 12 (growth 2) with a 64-entry table: level 0 has exactly 4^3 = 64 vertices and is
    dense, the others are hashed. Every output, at random points, on the faces and at x = 1, is the
    reference's (so a saved model means the same after any rewrite of the encoding)."""
    torch.manual_seed(0)
    h = HashGrid(num_levels=3, features_per_level=2, log2_table_size=6, base_resolution=3, max_resolution=12,
                 init_scale=1.0).double()
    assert h.resolution.tolist() == [3.0, 6.0, 12.0]
    assert h.dense.tolist() == [True, False, False]
    assert h.level_size.tolist() == [64, 64, 64] and h.offset.tolist() == [0, 64, 128]
    assert h.level_size.dtype == h.offset.dtype == torch.long
    assert list(h.state_dict()) == ["table"] and h.table.shape == (192, 2)   # the rest is derived, not saved
    assert h.out_dim == 6
    rng = np.random.default_rng(1)
    x = np.concatenate([rng.uniform(size=(40, 3)), [[1.0, 1.0, 1.0], [0.0, 0.5, 1.0], [1 / 3, 2 / 3, 0.999999]]])
    want = _hashgrid_reference(h.table.detach().numpy(), [3, 6, 12], [True, False, False], 64, x)
    got = h(torch.from_numpy(x)).detach().numpy()
    assert np.allclose(got, want, rtol=1e-12, atol=1e-12)
    # batch shape kept
    assert h(torch.from_numpy(x[:6]).reshape(2, 3, 3)).shape == (2, 3, 6)


def test_hashgrid_levels_sizes_and_initial_table():
    two = HashGrid(num_levels=2, features_per_level=2, log2_table_size=6, base_resolution=4, max_resolution=16,
                   init_scale=0.5)
    assert two.resolution.tolist() == [4.0, 16.0]                    # growth over num_levels - 1 = 1 step
    assert two.dense.tolist() == [False, False]                      # 5^3 = 125 > 64: hashed (3^3 would fit)
    t = two.table.detach()
    assert t.abs().max() <= 0.5 and t.min() < -0.25 and t.max() > 0.25   # uniform in [-init_scale, init_scale]
    one = HashGrid(num_levels=1, features_per_level=3, log2_table_size=6, base_resolution=2, max_resolution=2)
    assert one.resolution.tolist() == [2.0] and one.dense.tolist() == [True]
    assert one.level_size.tolist() == [27] and one.table.shape == (27, 3)   # a dense level holds (r+1)^3 rows


def test_fourier_features_are_sin_and_cos_of_pi_times_powers_of_two():
    x = torch.rand(5, 2, dtype=torch.float64)
    f = FourierFeatures(2, 3)
    assert list(f.state_dict()) == []
    want = [x] + [torch.sin(math.pi * 2 ** k * x[:, [d]]) for d in range(2) for k in range(3)] + \
        [torch.cos(math.pi * 2 ** k * x[:, [d]]) for d in range(2) for k in range(3)]
    assert torch.allclose(f(x), torch.cat(want, -1), atol=1e-6)
    g = FourierFeatures(2, 3, include_input=False)
    assert g.out_dim == 12 and torch.allclose(g(x), torch.cat(want[1:], -1), atol=1e-6)


def test_mlp_has_the_asked_hidden_layers():
    net = mlp(3, 4, 8, 3)
    linears = [m for m in net if isinstance(m, torch.nn.Linear)]
    assert [(m.in_features, m.out_features) for m in linears] == [(3, 8), (8, 8), (8, 8), (8, 4)]
    assert [(m.in_features, m.out_features) for m in mlp(3, 4, 8, 0)] == [(3, 4)]


class _Features(torch.nn.Module):
    """A stand-in for the frozen SDF's feature field: ``f(x) = (x0 x1, sin x2)``."""

    dim = 2

    def forward(self, x):
        return torch.stack([x[..., 0] * x[..., 1], torch.sin(x[..., 2])], -1)


def test_material_field_scales_points_into_its_own_box_and_reads_the_features_at_x():
    torch.manual_seed(4)
    lo, hi = torch.tensor([-2.0, 1.0, 0.5]), torch.tensor([2.0, 3.0, 4.5])
    field = MaterialField(FourierFeatures(3, 2), 8, 1, (lo, hi), features=_Features())
    assert field.box_lo.dtype == field.box_size.dtype == torch.float32
    assert torch.equal(field.box_size, hi - lo)
    assert field.net[0].in_features == field.encoding.out_dim + 2
    x = lo + torch.rand(6, 3) * (hi - lo)
    h = torch.cat([field.encoding((x - lo) / (hi - lo)), _Features()(x)], -1)
    out = field.net(h)
    mat = field(x)
    assert torch.allclose(mat.albedo, torch.sigmoid(out[:, :3]), atol=1e-6)
    assert torch.allclose(mat.roughness, 0.911 * torch.sigmoid(out[:, 3]) + 0.089, atol=1e-6)
    batched = field(x.reshape(2, 3, 3))                              # any batch shape
    assert torch.allclose(batched.albedo.reshape(6, 3), mat.albedo, atol=1e-6)
    # with a normal offset the encoding reads x + offset n, the features still x itself
    sided = MaterialField(FourierFeatures(3, 2), 8, 1, (lo, hi), features=_Features(), normal_offset=0.1)
    n = torch.nn.functional.normalize(torch.randn(6, 3), dim=-1)
    h = torch.cat([sided.encoding((x + 0.1 * n - lo) / (hi - lo)), _Features()(x)], -1)
    assert torch.allclose(sided(x, n).albedo, torch.sigmoid(sided.net(h)[:, :3]), atol=1e-6)
    with pytest.raises(ValueError, match=r"^this material field encodes x \+ offset \* n: pass the surface normals$"):
        sided(x)


# ---------------------------------------------------------------------------- render/

def test_schlick_fresnel_clamps_the_cosine():
    f0 = 0.04
    c = torch.tensor([-0.5, 0.0, 0.3, 1.0, 1.5], dtype=torch.float64)
    want = torch.tensor([1.0, 1.0, f0 + (1 - f0) * 0.7 ** 5, f0, f0], dtype=torch.float64)
    assert torch.allclose(F_schlick(c, f0), want, rtol=1e-12)


def test_envmap_lookup_at_the_poles_reads_the_first_and_last_rows():
    H, W = 4, 8
    image = torch.arange(H * W * 3, dtype=torch.float32).reshape(H, W, 3)
    up, down = torch.tensor([[0.0, 0.0, 1.0]]), torch.tensor([[0.0, 0.0, -1.0]])
    assert int(envmap_lookup(image, up)[0, 0]) // (W * 3) == 0
    assert int(envmap_lookup(image, down)[0, 0]) // (W * 3) == H - 1


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
