"""Mesh ray casting against analytic spheres and planes."""
import math

import numpy as np
import pytest
import torch
import trimesh

from nefii.errors import InputError
from nefii.raycast import MeshGeometry, Rays, spawn_rays
from nefii.render.frame import dot, normalize


@pytest.fixture(scope="module")
def sphere():
    m = trimesh.creation.icosphere(subdivisions=5, radius=1.0)
    return MeshGeometry(m.vertices, m.faces)


@pytest.fixture(scope="module")
def plane():
    # the square [-1,1]^2 at z = 0.5, normal +z (counter-clockwise seen from above)
    v = np.array([[-1, -1, 0.5], [1, -1, 0.5], [1, 1, 0.5], [-1, 1, 0.5]], float)
    f = np.array([[0, 1, 2], [0, 2, 3]])
    return MeshGeometry(v, f)


def random_rays(n, gen, spread=3.0):
    o = torch.randn(n, 3, generator=gen) * spread
    target = torch.randn(n, 3, generator=gen) * 0.5
    return Rays(o, normalize(target - o))


def analytic_sphere_t(rays):
    b = dot(rays.origins, rays.directions)
    disc = b * b - (dot(rays.origins, rays.origins) - 1.0)
    t0 = -b - disc.clamp_min(0).sqrt()
    t1 = -b + disc.clamp_min(0).sqrt()
    t = torch.where(t0 > 0, t0, t1)
    return torch.where((disc > 0) & (t > 0), t, torch.full_like(t, math.inf))


def test_sphere_hits_match_analytic(sphere):
    g = torch.Generator().manual_seed(0)
    rays = random_rays(20000, g)
    hit = sphere.intersect(rays)
    t_ref = analytic_sphere_t(rays)
    # the tessellated sphere lies inside the unit sphere by at most ~3e-4 (subdivision 5)
    both = hit.valid & torch.isfinite(t_ref)
    disagree = (hit.valid != torch.isfinite(t_ref)).float().mean()
    assert disagree < 0.005  # only grazing rays may disagree
    assert (hit.t[both] - t_ref[both]).abs().max() < 0.05
    assert ((hit.position[both].norm(dim=-1) - 1).abs() < 1e-3).all()
    # interpolated normals of a sphere are its radial directions
    assert (dot(hit.normal[both], normalize(hit.position[both])) > 0.999).all()
    assert (dot(hit.geometric_normal[both], normalize(hit.position[both])) > 0.99).all()
    assert (hit.triangle_id[~hit.valid] == -1).all() and (hit.triangle_id[hit.valid] >= 0).all()
    assert torch.isinf(hit.t[~hit.valid]).all()


def test_plane_hits_are_exact(plane):
    g = torch.Generator().manual_seed(1)
    o = torch.cat([torch.rand(5000, 2, generator=g) * 1.6 - 0.8, torch.full((5000, 1), 3.0)], -1)
    d = normalize(torch.cat([torch.randn(5000, 2, generator=g) * 0.1, -torch.ones(5000, 1)], -1))
    hit = plane.intersect(Rays(o, d))
    t_ref = (o[:, 2] - 0.5) / -d[:, 2]
    inside = ((o + t_ref.unsqueeze(-1) * d)[:, :2].abs() < 0.999).all(-1)
    assert hit.valid[inside].all()
    assert torch.allclose(hit.t[inside], t_ref[inside], atol=1e-5)
    assert torch.allclose(hit.position[inside, 2], torch.full_like(t_ref[inside], 0.5), atol=1e-6)
    assert torch.allclose(hit.normal[inside], torch.tensor([0.0, 0.0, 1.0]).expand(int(inside.sum()), 3))


def test_occluded_agrees_with_intersect_and_t_max(sphere):
    g = torch.Generator().manual_seed(2)
    rays = random_rays(20000, g)
    hit = sphere.intersect(rays)
    assert torch.equal(sphere.occluded(rays), hit.valid)
    # a ray that stops before its hit is not occluded
    short = Rays(rays.origins, rays.directions, t_max=torch.where(hit.valid, hit.t * 0.9, torch.full_like(hit.t, 1e3)))
    assert not sphere.occluded(short)[hit.valid].any()
    assert not sphere.intersect(short).valid[hit.valid].any()


def test_spawned_rays_do_not_hit_their_own_surface(sphere):
    g = torch.Generator().manual_seed(3)
    rays = random_rays(20000, g)
    hit = sphere.intersect(rays)
    x, ng = hit.position[hit.valid], hit.geometric_normal[hit.valid]
    # outgoing directions in the upper hemisphere of the convex sphere never hit it
    d = normalize(torch.randn(x.shape, generator=g))
    d = torch.where(dot(d, ng).unsqueeze(-1) < 0, -d, d)
    out = spawn_rays(x, ng, d, offset=1e-4 * sphere.scale)
    assert not sphere.occluded(out).any()
    # directions into the surface hit the far side, at about the chord length
    inward = spawn_rays(x, ng, -d, offset=1e-4 * sphere.scale)
    h2 = sphere.intersect(inward)
    assert h2.valid.float().mean() > 0.999
    chord = 2 * dot(-d, -normalize(x))
    ok = h2.valid & (chord > 0.2)  # near-tangent rays may leave through a neighbouring facet
    assert ((h2.t[ok] - chord[ok]).abs() < 0.01).all()


def test_batch_shapes_and_dtype_are_kept(sphere):
    o = torch.tensor([0.0, 0.0, -3.0], dtype=torch.float64).expand(4, 5, 3)
    d = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64).expand(4, 5, 3)
    hit = sphere.intersect(Rays(o, d))
    assert hit.position.shape == (4, 5, 3) and hit.valid.shape == (4, 5)
    assert hit.position.dtype == torch.float64 and hit.valid.all()
    empty = sphere.intersect(Rays(torch.zeros(0, 3), torch.zeros(0, 3)))
    assert empty.position.shape == (0, 3)


def test_bad_mesh_files_name_the_file(tmp_path):
    with pytest.raises(InputError, match="mesh file not found"):
        MeshGeometry.from_file(tmp_path / "nope.ply")
    bad = tmp_path / "bad.ply"
    bad.write_text("this is not a ply file")
    with pytest.raises(InputError) as e:
        MeshGeometry.from_file(bad)
    assert str(bad) in str(e.value)


def test_lookup_normals_are_interpolated_beside_the_shading_normals(sphere, tmp_path):
    """A mesh's material-lookup normals are its shading normals unless given; given, a hit carries both,
    each interpolated from its own vertex array. ``from_file(lookup_sigma=...)`` smooths only the lookup's."""
    rays = random_rays(4000, torch.Generator().manual_seed(3))
    hit = sphere.intersect(rays)
    assert torch.equal(hit.lookup_normal, hit.normal)
    flipped = MeshGeometry(sphere.vertices, sphere.faces, lookup_normals=-sphere.vertex_normals)
    other = flipped.intersect(rays)
    v = other.valid
    assert v.sum() > 1000
    torch.testing.assert_close(other.normal[v], hit.normal[v])
    torch.testing.assert_close(other.lookup_normal[v], -hit.normal[v])
    with pytest.raises(ValueError, match="one normal per vertex"):
        MeshGeometry(sphere.vertices, sphere.faces, lookup_normals=sphere.vertex_normals[:-1])

    bumpy = trimesh.creation.icosphere(subdivisions=4)
    rng = np.random.default_rng(0)
    bumpy.vertices = bumpy.vertices * (1 + 0.02 * rng.normal(size=(len(bumpy.vertices), 1)))
    bumpy.export(tmp_path / "bumpy.ply")
    mesh = MeshGeometry.from_file(tmp_path / "bumpy.ply", lookup_sigma=0.05)
    radial = bumpy.vertices / np.linalg.norm(bumpy.vertices, axis=-1, keepdims=True)
    err = lambda n: np.degrees(np.arccos(np.clip((n * radial).sum(-1), -1, 1))).mean()  # noqa: E731
    plain = MeshGeometry.from_file(tmp_path / "bumpy.ply")
    assert np.allclose(mesh.vertex_normals, plain.vertex_normals, atol=1e-6)   # shading normals untouched
    assert err(mesh.lookup_normals) < 0.5 * err(mesh.vertex_normals)


@pytest.fixture(scope="module")
def hollow_ball(tmp_path_factory):
    """A ball of radius 1 with a cavity of radius 0.9 (inner faces wound towards the centre): a wall 0.1 thick."""
    outer = trimesh.creation.icosphere(subdivisions=4, radius=1.0)
    inner = trimesh.creation.icosphere(subdivisions=4, radius=0.9)
    inner.invert()
    mesh = trimesh.util.concatenate([outer, inner])
    path = tmp_path_factory.mktemp("hollow") / "hollow.ply"
    mesh.export(path)
    return path


def test_normals_interpolate_to_unit_length_and_hit_the_vertices():
    """The interpolated normal is unit; at a corner (barycentric one-hot) it is that vertex's normal; for
    vertex normals all equal, it is that normal."""
    from nefii.raycast.mesh import interpolate_normals
    gen = torch.Generator().manual_seed(0)
    n = normalize(torch.randn(500, 3, 3, generator=gen) + torch.tensor([0.0, 0.0, 3.0]))
    b = torch.rand(500, 3, generator=gen)
    b = b / b.sum(-1, keepdim=True)
    out = interpolate_normals(n, b)
    torch.testing.assert_close(out.norm(dim=-1), torch.ones(500))
    corner = torch.nn.functional.one_hot(torch.randint(3, (500,), generator=gen), 3).float()
    torch.testing.assert_close(interpolate_normals(n, corner), (n * corner.unsqueeze(-1)).sum(-2))
    same = n[:, :1].expand(500, 3, 3)
    torch.testing.assert_close(interpolate_normals(same, b), n[:, 0])
