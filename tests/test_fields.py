"""Fields: hash-grid encoding (gradients, interpolation), activations, SG environment initialisation."""
import math

import pytest
import torch
from torch.func import functional_call

from autograd_graph import graph_names

from nefii.fields.encodings import FourierFeatures, HashGrid, _Gather
from nefii.fields.environment import EnvmapEnvironment, SGEnvironment
from nefii.fields.material import MaterialField
from nefii.render.equirect import pixel_directions, pixel_solid_angles


def test_hashgrid_gradient_matches_finite_differences():
    torch.manual_seed(0)
    h = HashGrid(num_levels=4, features_per_level=2, log2_table_size=8, base_resolution=3, max_resolution=40,
                 init_scale=1.0).double()
    x = torch.rand(30, 3, dtype=torch.float64)
    table = h.table.detach().clone().requires_grad_()
    f = lambda t: functional_call(h, {"table": t}, (x,))
    assert torch.autograd.gradcheck(f, (table,))


def test_hashgrid_position_gradient_and_double_backward_match_finite_differences():
    """The SDF stage trains through d encoding / d x (the eikonal loss): first and second derivatives
    with respect to the points and the table, dense and hashed levels, checked in float64."""
    torch.manual_seed(2)
    h = HashGrid(num_levels=3, features_per_level=2, log2_table_size=6, base_resolution=2, max_resolution=9,
                 init_scale=1.0).double()
    assert bool(h.dense[0]) and not bool(h.dense[-1])
    x = (torch.rand(12, 3, dtype=torch.float64) * 0.9 + 0.05).requires_grad_()
    table = h.table.detach().clone().requires_grad_()
    f = lambda p, t: functional_call(h, {"table": t}, (p,))
    assert torch.autograd.gradcheck(f, (x, table))
    assert torch.autograd.gradgradcheck(f, (x, table))


def test_hashgrid_float32_gather_reads_and_scatters_the_same_rows():
    """Two float32 features are gathered as one float64 word (a fast path): bit for bit ``table[idx]``, and its
    backward the sum of the gradients of each row's reads, for repeated and for unused rows alike."""
    torch.manual_seed(3)
    table = torch.randn(50, 2, requires_grad=True)
    idx = torch.randint(0, 40, (7, 3, 8))                      # rows 40-49 never read, others read often
    rows = _Gather.apply(table, idx)
    assert rows.dtype == torch.float32 and torch.equal(rows, table.detach()[idx])
    grad = torch.randn(7, 3, 8, 2)
    rows.backward(grad)
    want = torch.zeros(50, 2).index_put_((idx.reshape(-1),), grad.reshape(-1, 2), accumulate=True)
    assert torch.allclose(table.grad, want, atol=1e-6) and not table.grad[40:].any()
    odd = torch.randn(50, 3)                                   # three features: the plain row gather
    assert torch.equal(_Gather.apply(odd, idx), odd[idx])


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_hashgrid_compiled_cpu_path_matches_the_pytorch_path(dtype):
    """Points without a gradient take the compiled loop (nefii.fields.hashgrid_cpu); points with one the PyTorch
    path. Same features and the same table gradient for random cotangents, over dense and hashed levels, points on
    the box's faces and outside it (clamped)."""
    torch.manual_seed(4)
    h = HashGrid(num_levels=6, features_per_level=2, log2_table_size=9, base_resolution=2, max_resolution=60,
                 init_scale=1.0).to(dtype)
    assert bool(h.dense[0]) and not bool(h.dense[-1])
    x = torch.rand(400, 3, dtype=dtype) * 1.2 - 0.1
    x[:6] = torch.tensor([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0], [1.0, 0.5, 0.0], [0.5, 0.25, 1.0], [-2.0, 3.0, 0.5],
                          [1 / 3, 2 / 3, 0.999999]], dtype=dtype)
    fast = h(x)
    assert "FusedHashEncodeBackward" in graph_names(fast)
    slow = h(x.clone().requires_grad_())
    assert slow.grad_fn is not None and "FusedHashEncodeBackward" not in graph_names(slow)
    tol = dict(rtol=1e-5, atol=1e-5) if dtype == torch.float32 else dict(rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(fast, slow.detach(), **tol)
    cot = torch.randn(fast.shape, dtype=dtype)
    g_fast, = torch.autograd.grad((fast * cot).sum(), h.table)
    g_slow, = torch.autograd.grad((slow * cot).sum(), h.table)
    torch.testing.assert_close(g_fast, g_slow, **tol)


def test_hashgrid_is_continuous_and_exact_on_dense_vertices():
    torch.manual_seed(1)
    h = HashGrid(num_levels=1, features_per_level=2, log2_table_size=12, base_resolution=8, max_resolution=8,
                 init_scale=1.0)
    assert bool(h.dense[0])
    # a grid vertex returns its own table entry
    ijk = torch.tensor([[3, 5, 2]])
    out = h(ijk.float() / 8.0)
    idx = 3 + 9 * (5 + 9 * 2)
    assert torch.allclose(out[0], h.table[idx], atol=1e-6)
    # trilinear interpolation is continuous across cell faces
    x = torch.rand(500, 3) * 0.9 + 0.05
    x[:, 0] = (torch.randint(1, 7, (500,)).float()) / 8.0
    e = torch.tensor([1e-5, 0.0, 0.0])
    assert (h(x + e) - h(x - e)).abs().max() < 1e-3


def test_hashgrid_levels_have_the_asked_resolutions():
    h = HashGrid(num_levels=6, features_per_level=2, log2_table_size=14, base_resolution=4, max_resolution=128)
    assert int(h.resolution[0]) == 4 and int(h.resolution[-1]) == 128
    assert h.out_dim == 12 and h(torch.rand(5, 3)).shape == (5, 12)
    # the coarse levels are dense, the fine ones hashed
    assert bool(h.dense[0]) and not bool(h.dense[-1])


def test_fourier_features():
    f = FourierFeatures(3, 4)
    x = torch.rand(7, 3)
    y = f(x)
    assert y.shape == (7, f.out_dim) == (7, 27)
    assert torch.allclose(y[:, :3], x)
    assert torch.allclose(y[:, 3:15], torch.sin((x.unsqueeze(-1) * f.freqs).flatten(-2)))


def test_material_field_ranges_and_override():
    torch.manual_seed(2)
    box = (torch.zeros(3), torch.ones(3))
    m = MaterialField(HashGrid(4, 2, 10, 4, 32, init_scale=3.0), 16, 1, box)
    mat = m(torch.rand(1000, 3) * 3 - 1)  # outside the box too
    assert mat.albedo.min() > 0 and mat.albedo.max() < 1
    assert mat.roughness.min() >= 0.089 - 1e-6 and mat.roughness.max() <= 1.0 + 1e-6
    fixed = m(torch.rand(10, 3), roughness_override=0.5)
    assert torch.all(fixed.roughness == 0.5)


def test_material_normal_offset_encodes_the_offset_point_and_separates_thin_wall_faces():
    torch.manual_seed(3)
    box = (torch.zeros(3), torch.ones(3))
    plain = MaterialField(HashGrid(4, 2, 12, 4, 16, init_scale=3.0), 16, 1, box)   # cells > the wall
    sided = MaterialField(HashGrid(4, 2, 12, 4, 16, init_scale=3.0), 16, 1, box, normal_offset=0.1)
    sided.load_state_dict(plain.state_dict())
    x = 0.3 + 0.4 * torch.rand(200, 3)
    n = torch.nn.functional.normalize(torch.randn(200, 3), dim=-1)
    assert torch.allclose(sided(x, n).albedo, plain(x + 0.1 * n).albedo)
    # the two faces of a wall 0.01 thick: the same material without the offset, not with it
    face_in, face_out = x, x + 0.01 * n
    gap_plain = (plain(face_in).albedo - plain(face_out).albedo).abs().mean()
    gap_sided = (sided(face_in, -n).albedo - sided(face_out, n).albedo).abs().mean()
    assert gap_sided > 5 * gap_plain
    with pytest.raises(ValueError, match="normals"):
        sided(x)


@pytest.mark.parametrize("lobes", [16, 128])
def test_sg_environment_starts_near_a_constant_radiance(lobes):
    env = SGEnvironment(num_lobes=lobes, sharpness_min=5.0, sharpness_max=3000.0, init_radiance=0.5)
    with torch.no_grad():
        sg = env()
    assert torch.allclose(sg.axis.norm(dim=-1), torch.ones(lobes))
    assert sg.sharpness.min().item() == pytest.approx(5.0, rel=1e-4) and sg.sharpness.max().item() == pytest.approx(3000.0, rel=1e-4)
    # its mean radiance over the sphere (quadrature) is the asked one
    d = pixel_directions(512, 1024, dtype=torch.float64)
    w = pixel_solid_angles(512, 1024, dtype=torch.float64)
    with torch.no_grad():
        img = env.double().radiance(d)
    mean = (img * w.unsqueeze(-1)).sum((0, 1)) / (4 * math.pi)
    assert torch.allclose(mean, torch.full((3,), 0.5, dtype=torch.float64), rtol=0.03)


def test_envmap_environment_lookup():
    env = EnvmapEnvironment(8, 16, init_radiance=0.25)
    with torch.no_grad():
        env.log_radiance[0, 4] = math.log(7.0)  # a pixel of the top row
    d = pixel_directions(8, 16)[0, 4]
    assert env.radiance(d.unsqueeze(0))[0].tolist() == pytest.approx([7.0] * 3)
    assert env.to_equirect(8, 16)[0, 4].tolist() == pytest.approx([7.0] * 3)
