"""One decode of the material: on a mesh whose material lookup has its own smoothed normals (what
``nefii fit --geometry`` uses), the fit's decode, eval's render, relight's path tracer and export's bake
all read the same albedo at the same surface points."""
import numpy as np
import torch
import trimesh

from nefii.camera import intrinsics_from_fov, look_at, pixel_rays
from nefii.data.scene import Cameras
from nefii.evaluate.render_views import render_view
from nefii.fit.build import build_model
from nefii.fit.config import resolve_config
from nefii.fit.model import decode_material, material_at
from nefii.raycast import MeshGeometry, Rays
from nefii.raycast.mesh import interpolate_normals
from nefii.render.envmap import Environment
from nefii.relight.pathtracer import PathSettings, trace_paths
from nefii.render.brdf import Material


def bumpy_ball(tmp_path) -> MeshGeometry:
    """A ball with noisy vertices, its lookup normals smoothed far more than its shading normals."""
    ball = trimesh.creation.icosphere(subdivisions=3)
    rng = np.random.default_rng(0)
    ball.vertices += 0.03 * rng.normal(size=ball.vertices.shape)
    ball.export(tmp_path / "ball.ply")
    return MeshGeometry.from_file(tmp_path / "ball.ply", lookup_sigma=0.1)


def random_model(geometry: MeshGeometry):
    box = tuple(torch.from_numpy(b.copy()) for b in geometry.bounds)
    model = build_model(resolve_config("tiny", ["material_offset=0.2"]), box)
    with torch.no_grad():
        for p in model.material.parameters():
            p.copy_(torch.randn(p.shape, generator=torch.Generator().manual_seed(3)))
    return model.eval()


def test_fit_eval_relight_and_bake_read_the_same_material(tmp_path):
    geometry = bumpy_ball(tmp_path)
    model = random_model(geometry)
    res = 24
    c2w = look_at(torch.tensor([0.0, -4.0, 1.0], dtype=torch.float64), torch.zeros(3, dtype=torch.float64),
                  torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))
    K = intrinsics_from_fov(np.radians(40.0), res, res)
    o, d = pixel_rays(c2w, K, res, res)
    rays = Rays(o.reshape(-1, 3).float(), d.reshape(-1, 3).float())
    hit = geometry.intersect(rays)
    assert hit.valid.sum() > 100
    # the lookup normals differ from the shading normals, so reading along the wrong one shows
    assert (hit.lookup_normal[hit.valid] - hit.normal[hit.valid]).norm(dim=-1).max() > 0.1

    with torch.no_grad():
        fit_albedo = decode_material(model, hit.position[hit.valid], hit.lookup_normal[hit.valid]).albedo
        wrong = decode_material(model, hit.position[hit.valid], hit.normal[hit.valid]).albedo
    assert (fit_albedo - wrong).abs().max() > 1e-2

    # eval: the albedo layer of a rendered view (its layers on the 1-spp colour's ray, the pixel centre, to
    # compare point by point; eval itself averages 4 x 4 of them)
    cams = Cameras(K.unsqueeze(0), c2w.unsqueeze(0), res, res)
    pred = render_view(model, geometry, cams, 0, 1, torch.Generator().manual_seed(0), filtered_layers=False)
    torch.testing.assert_close(pred.albedo.reshape(-1, 3)[hit.valid], fit_albedo)

    # relight: what the path tracer's material function is asked at the first bounce
    seen: list[tuple[torch.Tensor, Material]] = []

    def recorded(x, lookup_normal):
        m = decode_material(model, x, lookup_normal)
        seen.append((x.clone(), m))
        return m

    env = Environment.from_image(torch.ones(8, 16, 3))
    trace_paths(rays, geometry, recorded, env, torch.Generator().manual_seed(0), PathSettings(max_bounces=1))
    x_relit, m_relit = seen[0]
    front = hit.position[hit.valid]
    order = torch.cdist(x_relit, front).argmin(-1)
    torch.testing.assert_close(x_relit, front[order])
    torch.testing.assert_close(m_relit.albedo, fit_albedo[order])

    # export's bake: texels decode along the vertex lookup normals interpolated as the ray caster does
    tri = torch.from_numpy(geometry.faces[hit.triangle_id[hit.valid].numpy()].astype(np.int64))
    corners = torch.from_numpy(geometry.vertices)[tri].double()
    bary = torch.linalg.lstsq(torch.cat([corners.transpose(1, 2), torch.ones(len(tri), 1, 3, dtype=torch.float64)], 1),
                              torch.cat([front.double(), torch.ones(len(tri), 1, dtype=torch.float64)], 1)
                              .unsqueeze(-1)).solution.squeeze(-1)
    lookup = interpolate_normals(torch.from_numpy(geometry.lookup_normals)[tri].double(), bary).float()
    baked = material_at(model, front, lookup).albedo
    torch.testing.assert_close(baked, fit_albedo, atol=1e-4, rtol=0)
