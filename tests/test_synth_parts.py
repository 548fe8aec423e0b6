"""nefii.synth without Mitsuba: meshes, textures, skies, env-map baking, cameras."""
import math

import numpy as np
import pytest
import torch

from nefii.render.equirect import pixel_directions, pixel_solid_angles
from nefii.synth import cameras, envmaps, meshes, noise, scenes, skies
from nefii.synth.mitsuba_backend import bake_for_mitsuba, mitsuba_grid, mitsuba_uv_to_direction


# ---------------------------------------------------------------- scenes and meshes

@pytest.mark.parametrize("name", scenes.scene_names())
def test_scene_geometry_is_closed_form_sane(name):
    """Outward normals agree with the winding, moderate size, centred, inside a unit-ish sphere."""
    built = scenes.build_scene(name, texture_tile=32)
    m = built.atlas.mesh
    assert 1000 < len(m.faces) <= 50_000
    agree = (m.face_normals() * m.normals[m.faces].sum(1)).sum(-1)
    assert (agree > 0).all(), f"{int((agree <= 0).sum())} faces wound against their normals"
    assert np.allclose(np.linalg.norm(m.normals, axis=-1), 1.0, atol=1e-6)
    lo, hi = m.vertices.min(0), m.vertices.max(0)
    assert np.allclose(lo + hi, 0.0, atol=1e-9)
    assert 0.6 < built.radius < 1.15
    assert ((m.uv >= 0) & (m.uv <= 1)).all()
    assert built.atlas.base_color.min() >= 0.03 and built.atlas.base_color.max() <= 0.9
    assert built.atlas.roughness.min() >= 0.1 and built.atlas.roughness.max() <= 0.95
    # spatially varying materials, not constants
    assert built.atlas.base_color.std() > 0.05 and built.atlas.roughness.std() > 0.05


def test_there_are_four_scenes_under_hard_and_soft_light_and_a_smallest():
    names = scenes.scene_names()
    assert len(names) >= 4
    lighting = {skies.get_environment(scenes.SCENES[n].environment).lighting for n in names}
    assert lighting == {"hard sun", "soft"}
    assert scenes.smallest_scene() == min(names, key=scenes.triangle_count)
    for spec in scenes.SCENES.values():
        assert spec.environment not in spec.relight and len(set(spec.relight)) == 2


def test_ply_round_trip(tmp_path):
    import trimesh

    m = meshes.torus(0.5, 0.2, 16, 8)
    meshes.write_ply(tmp_path / "t.ply", m)
    back = trimesh.load(tmp_path / "t.ply", process=False)
    assert np.allclose(back.vertices, m.vertices, atol=1e-6)
    assert np.array_equal(back.faces, m.faces)


def test_noise_is_deterministic_and_spread_over_unit_interval():
    a = noise.noise_tile(5)
    noise.noise_tile.cache_clear()
    b = noise.noise_tile(5)
    assert torch.equal(a, b)
    assert 0.0 <= float(a.min()) and float(a.max()) <= 1.0
    assert abs(float((a > 0.7).float().mean()) - 0.3) < 0.02  # thresholds mean coverage
    xy = torch.rand(100, 2)
    assert torch.allclose(noise.noise2(xy, 5), noise.noise2(xy + 3.0, 5), atol=1e-5)  # periodic


# ---------------------------------------------------------------- environments and baking

def _sun_only(diameter_deg: float = 1.0, radiance: float = 1000.0) -> skies.Environment:
    sun = skies.Sun(skies.direction(37.0, 123.0), (radiance,) * 3, diameter_deg)
    return skies.Environment("sun-only", "", "hard sun", lambda d: torch.zeros(d.shape), sun)


def test_equirect_bake_samples_the_background_at_nefii_pixel_centres():
    env = skies.Environment("dir", "", "soft", lambda d: d.float())
    baked = envmaps.bake_equirect(env, 16, 32)
    assert np.allclose(baked, pixel_directions(16, 32).numpy(), atol=1e-6)


@pytest.mark.parametrize("height", [32, 128, 512])
def test_sun_power_is_exact_on_both_grids(height):
    """The disc is integrated per texel: total power matches L * solid angle on nefii's grid and on
    Mitsuba's pole-to-pole grid, however few texels the sun covers."""
    env = _sun_only()
    exact = 1000.0 * env.sun.solid_angle()
    gt = envmaps.bake_equirect(env, height, 2 * height)
    power_gt = float((gt[..., 0] * pixel_solid_angles(height, 2 * height).numpy()).sum())
    mts = bake_for_mitsuba(env, height + 1, 2 * height)
    cell = mitsuba_grid(height + 1, 2 * height).row_solid_angle().numpy()
    assert cell.sum() * 2 * height == pytest.approx(4 * np.pi)
    power_mts = float((mts[..., 0] * cell[:, None]).sum())
    assert power_gt == pytest.approx(exact, rel=0.01)
    assert power_mts == pytest.approx(exact, rel=0.01)
    # and it is where the sun is
    i, j = np.unravel_index(np.argmax(gt[..., 0]), gt.shape[:2])
    d = pixel_directions(height, 2 * height)[i, j].numpy()
    assert math.degrees(math.acos(min(1.0, float(d @ np.array(env.sun.direction))))) < 180.0 / height + 0.5


@pytest.mark.parametrize("grid", [envmaps.equirect_grid(8, 16), mitsuba_grid(9, 16)])
def test_grid_texel_of_inverts_centres(grid):
    rows, cols = grid.texel_of(grid.centres())
    inner = slice(1, grid.height - 1)  # pole texels of Mitsuba's grid share one direction
    assert torch.equal(rows[inner], torch.arange(grid.height)[inner, None].expand(-1, grid.width))
    assert torch.equal(cols[inner], torch.arange(grid.width).expand(grid.height - 2, -1))


def test_mitsuba_grid_directions_match_the_documented_convention():
    u, v = torch.tensor([0.25, 0.5, 0.0]), torch.tensor([0.5, 0.5, 0.0])
    d = mitsuba_uv_to_direction(u, v)
    # local Y is world Z (v = 0 is the zenith); u = 0.25 looks along local +X = world +X
    assert torch.allclose(d, torch.tensor([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, 1.0]]), atol=1e-6)


@pytest.mark.parametrize("name", list(skies.ENVIRONMENTS))
def test_environments_are_hdr_and_hard_or_soft_as_labelled(name):
    env = skies.get_environment(name)
    img = envmaps.bake_equirect(env, 64, 128)
    assert np.isfinite(img).all() and img.min() >= 0.0
    lum = img.mean(-1)
    sky = float(np.median(lum[:32]))
    if env.lighting == "hard sun":
        assert env.sun is not None and 0.5 <= env.sun.angular_diameter_deg <= 1.5
        assert min(env.sun.radiance) / float(np.median(env.background(pixel_directions(32, 64)).mean(-1))) > 1000
    else:
        assert env.sun is None
        assert lum.max() / sky < 100
    # ground and sky differ (coloured ground below the horizon)
    assert abs(float(np.median(lum[40:])) - sky) > 0.02


# ---------------------------------------------------------------- cameras

def test_rig_views_are_disjoint_look_at_the_origin_and_frame_the_object():
    rig = cameras.make_rig(30, 7, 64, 1.0, (-10.0, 70.0), seed=3)
    assert rig.train.shape == (30, 4, 4) and rig.test.shape == (7, 4, 4)
    centres = np.concatenate([rig.train, rig.test])[:, :3, 3]
    assert len(np.unique(centres.round(6), axis=0)) == 37
    for c2w in np.concatenate([rig.train, rig.test]):
        R = c2w[:3, :3]
        assert np.allclose(R.T @ R, np.eye(3), atol=1e-9) and np.linalg.det(R) == pytest.approx(1.0)
        forward = -R[:, 2]  # OpenGL cameras look down -z
        assert np.allclose(forward, -c2w[:3, 3] / np.linalg.norm(c2w[:3, 3]), atol=1e-9)
        assert R[2, 1] > 0  # camera up has a positive world-Z component
        elev = math.degrees(math.asin(c2w[2, 3] / rig.distance))
        assert -10.0 <= elev <= 70.0
    # the unit sphere fits inside the horizontal field of view
    assert math.asin(1.0 / rig.distance) < rig.fov_x / 2
    meta = cameras.transforms_json(rig, rig.test, "test")
    assert meta["frames"][3]["file_path"] == "./test/r_3"
    assert meta["fl_x"] == pytest.approx(32 / math.tan(rig.fov_x / 2)) and meta["cx"] == 32


# ---------------------------------------------------------------- Mitsuba variant choice

def test_no_libllvm_falls_back_to_scalar_with_a_warning(monkeypatch):
    from nefii.synth import mitsuba_backend as mb

    monkeypatch.delenv(mb.VARIANT_ENV, raising=False)
    monkeypatch.delenv(mb.LLVM_ENV, raising=False)
    monkeypatch.setattr(mb, "find_libllvm", lambda: None)
    mb.select_variant.cache_clear()
    try:
        with pytest.warns(RuntimeWarning, match="libllvm19"):
            assert mb.select_variant() == "scalar_rgb"
    finally:
        mb.select_variant.cache_clear()


LLVM15 = "/usr/lib/x86_64-linux-gnu/libLLVM-15.so.1"


@pytest.mark.skipif(not __import__("os").path.exists(LLVM15), reason="needs Debian's libLLVM-15 to provoke the abort")
def test_a_libllvm_that_aborts_the_process_only_aborts_the_probe(tmp_path):
    """libLLVM-15 kills drjit's first llvm kernel with SIGABRT; the probe takes the blow."""
    import os
    import subprocess
    import sys

    pytest.importorskip("mitsuba")
    env = dict(os.environ, DRJIT_LIBLLVM_PATH=LLVM15)
    env.pop("NEFII_MITSUBA_VARIANT", None)
    r = subprocess.run([sys.executable, "-c", "from nefii.synth.mitsuba_backend import select_variant; "
                        "print(select_variant())"], env=env, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == "scalar_rgb"
    assert "falling back to Mitsuba's scalar_rgb" in r.stderr
