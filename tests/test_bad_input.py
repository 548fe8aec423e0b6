"""Bad input through the command line, table-driven: each case is a command, its exit code and the words its
one line must hold (docs/reliability.md). Settings are refused before any data is read: those cases point at
a dataset that does not exist, so the setting, not the data, has to be what the error names."""
from __future__ import annotations

import contextlib
import io
import json
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import pytest
import trimesh

from fit_fixtures import write_rendered_scene
from nefii.cli.main import main
from nefii.io.exr import read_exr, write_exr


@dataclass(frozen=True)
class Result:
    rc: int
    out: str
    err: str

    @property
    def errors(self) -> list[str]:
        return [line for line in self.err.splitlines() if ": error: " in line]

    @property
    def warnings(self) -> list[str]:
        return [line for line in (self.err + self.out).splitlines() if ": warning: " in line]


def cli(argv: list[str]) -> Result:
    """``nefii ARGV`` in this process, its exit code and what it printed."""
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        rc = main([str(a) for a in argv])
    return Result(rc, out.getvalue(), err.getvalue())


def assert_one_line_error(r: Result, *words: str) -> None:
    assert r.rc == 2, (r.rc, r.err[-2000:], r.out[-2000:])
    assert "Traceback" not in r.err
    assert len(r.errors) == 1, r.err
    for w in words:
        assert w in r.errors[0], (w, r.errors[0])


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> Path:
    return write_rendered_scene(tmp_path_factory.mktemp("scene") / "scene", res=16, n_train=6, n_test=2)


@pytest.fixture(scope="module")
def run(scene, tmp_path_factory) -> Path:
    """A finished tiny fit with two checkpoints."""
    out = tmp_path_factory.mktemp("run") / "run"
    r = cli(["fit", scene, "--out", out, "--preset", "tiny", "--quiet", "--set", "checkpoint_every_s=0",
             "--set", "threads=1"])
    assert r.rc == 0, r.err
    return out


# ---------------------------------------------------------------------------- the table

# Placeholders: {scene}, {run} (the fixtures), {tmp} (this case's folder), {missing} (no such dataset),
# {bad} (what the case's setup made).

def _scene_copy(scene: Path, tmp: Path) -> Path:
    return Path(shutil.copytree(scene, tmp / "bad"))


def setup_angle_zero(scene: Path, tmp: Path) -> Path:
    root = _scene_copy(scene, tmp)
    path = root / "transforms_train.json"
    meta = json.loads(path.read_text())
    for k in ("fl_x", "fl_y"):
        meta.pop(k)
    meta["camera_angle_x"] = 0
    path.write_text(json.dumps(meta))
    return root


def setup_equirectangular_capture(scene: Path, tmp: Path) -> Path:
    """A nerfstudio capture from a 360 camera, which nefii does not read."""
    root = tmp / "capture"
    root.mkdir()
    (root / "transforms.json").write_text(json.dumps({
        "camera_model": "EQUIRECTANGULAR", "fl_x": 8.0, "fl_y": 8.0, "w": 16, "h": 8,
        "frames": [{"file_path": "images/frame_00001.jpg", "transform_matrix": np.eye(4).tolist()}]}))
    return root


def setup_face_out_of_range(scene: Path, tmp: Path) -> Path:
    root = _scene_copy(scene, tmp)
    mesh = trimesh.load(root / "mesh.ply", force="mesh", process=False)
    faces = np.array(mesh.faces)
    faces[3, 1] = len(mesh.vertices) + 5
    header = ("ply\nformat ascii 1.0\nelement vertex {}\nproperty float x\nproperty float y\nproperty float z\n"
              "element face {}\nproperty list uchar int vertex_indices\nend_header\n").format(len(mesh.vertices),
                                                                                             len(faces))
    body = "".join(f"{x} {y} {z}\n" for x, y, z in mesh.vertices) + "".join(f"3 {a} {b} {c}\n" for a, b, c in faces)
    (root / "mesh.ply").write_text(header + body)
    return root


def setup_inverted_winding(scene: Path, tmp: Path) -> Path:
    """The mesh with every face wound the other way: its normals point into the object."""
    root = _scene_copy(scene, tmp)
    mesh = trimesh.load(root / "mesh.ply", force="mesh", process=False)
    trimesh.Trimesh(mesh.vertices, np.array(mesh.faces)[:, ::-1], process=False).export(root / "mesh.ply")
    return root


def setup_y_up_mesh(scene: Path, tmp: Path) -> Path:
    """The scene's mesh written as a glTF holds it: Y up, where the cameras' world is Z up."""
    root = _scene_copy(scene, tmp)
    mesh = trimesh.load(root / "mesh.ply", force="mesh", process=False)
    x, y, z = np.asarray(mesh.vertices).T
    trimesh.Trimesh(np.stack([x, z, -y], -1), mesh.faces, process=False).export(root / "mesh.ply")
    return root


def setup_huge_cameras(scene: Path, tmp: Path) -> Path:
    meta = json.loads((scene / "transforms_test.json").read_text())
    meta.update(w=1_000_000, h=1_000_000, fl_x=1e6, fl_y=1e6, cx=5e5, cy=5e5)
    meta["frames"] = meta["frames"][:1]
    path = tmp / "cameras.json"
    path.write_text(json.dumps(meta))
    return path


def setup_blinding_map(scene: Path, tmp: Path) -> Path:
    path = tmp / "sun.exr"
    write_exr(path, np.full((32, 64, 3), 3e38, np.float32))
    return path


def setup_foreign_folder(scene: Path, tmp: Path) -> Path:
    d = tmp / "mine"
    d.mkdir()
    (d / "config.json").write_text("{\"mine\": true}")
    (d / "model.pt").write_bytes(b"my own model")
    return d


def setup_a_file(scene: Path, tmp: Path) -> Path:
    path = tmp / "notes.txt"
    path.write_text("mine")
    return path


def setup_export_beside_others(scene: Path, tmp: Path) -> Path:
    d = tmp / "D"
    d.mkdir()
    (d / "README.txt").write_text("my notes")
    return d / "x.glb"


@dataclass(frozen=True)
class Case:
    name: str
    argv: str
    rc: int
    words: tuple[str, ...]
    setup: Callable[[Path, Path], Path] | None = None


FIT = "fit {missing} --out {tmp}/out --preset tiny --quiet"
GEO = "geometry {missing} --out {tmp}/out --preset tiny --quiet"
CASES = [
    # ---- fit settings, refused before the (missing) dataset is looked at
    Case("num_samples=-1", FIT + " --set num_samples=-1", 2, ("num_samples", "-1", "below 1")),
    Case("num_samples=0", FIT + " --set num_samples=0", 2, ("num_samples", "below 1")),
    Case("num_samples=1 with l2_pair", FIT + " --set num_samples=1", 2, ("num_samples", "l2_pair")),
    Case("batch_pixels=-3", FIT + " --set batch_pixels=-3", 2, ("batch_pixels", "-3")),
    Case("loss=bogus", FIT + " --set loss=bogus", 2, ("loss: 'bogus' is not one of l1, l2, l2_pair",)),
    Case("tonemap=bogus", FIT + " --set tonemap=bogus", 2, ("tonemap", "none, log1p")),
    Case("encoding kind", FIT + " --set material.encoding.kind=bogus", 2, ("material.encoding.kind", "hashgrid")),
    Case("light.kind=bogus", FIT + " --set light.kind=bogus", 2, ("light.kind", "sg, envmap")),
    Case("brdf.diffuse=lamber", FIT + " --set brdf.diffuse=lamber", 2,
         ("brdf.diffuse: 'lamber' is not one of burley, lambert; did you mean 'lambert'?",)),
    Case("light.num_lobes=0", FIT + " --set light.num_lobes=0", 2, ("light.num_lobes", "below 1")),
    Case("threads=-1", FIT + " --set threads=-1", 2, ("threads", "below 0")),
    Case("steps=0", FIT + " --set steps=0", 2, ("steps", "below 1")),
    Case("lr=-1", FIT + " --set lr=-1", 2, ("lr", "not above 0")),
    Case("lr=nan", FIT + " --set lr=nan", 2, ("lr", "not a finite number")),
    Case("material.hidden=0", FIT + " --set material.hidden=0", 2, ("material.hidden", "below 1")),
    Case("light.init=shadng", FIT + " --set light.init=shadng", 2,
         ("light.init: 'shadng' is not one of shading, uniform; did you mean 'shading'?",)),
    Case("a word for a number", FIT + " --set steps=many", 2, ("steps", "expected a whole number")),
    Case("unknown key, near", FIT + " --set light.nit=x", 2, ("light.nit", "did you mean 'light.init'?")),
    Case("unknown section, near", FIT + " --set materal.hidden=8", 2, ("did you mean 'material.hidden'?",)),
    Case("more than the machine holds", FIT + " --set batch_pixels=1000000000", 2, ("batch_pixels", "GiB")),
    Case("hash table too large", FIT + " --set material.encoding.log2_table_size=40", 2, ("log2_table_size",)),
    Case("--device bogus", FIT + " --device bogus", 2, ("--device bogus", "not a device")),
    Case("fit --out is a file", "fit {scene} --out {bad} --preset tiny --quiet", 2, ("notes.txt", "not a folder"),
         setup_a_file),
    Case("fit --out a foreign folder", "fit {scene} --out {bad} --preset tiny --quiet", 2,
         ("neither empty nor a nefii fit run",), setup_foreign_folder),
    Case("resume where no run is", "fit {scene} --out {tmp}/empty --preset tiny --quiet --resume", 2,
         ("no run to resume",)),
    Case("camera_angle_x=0", "fit {bad} --out {tmp}/out --preset tiny --quiet", 2,
         ("transforms_train.json", "camera_angle_x", "between 0"), setup_angle_zero),
    Case("nerfstudio camera_model", "fit {bad} --out {tmp}/out --preset tiny --quiet", 2,
         ("transforms.json", "'EQUIRECTANGULAR' is not supported"), setup_equirectangular_capture),
    Case("face index out of range", "fit {bad} --out {tmp}/out --preset tiny --quiet", 2,
         ("mesh.ply", "face 3 refers to vertex"), setup_face_out_of_range),
    Case("mesh wound inside out", "fit {bad} --out {tmp}/out --preset tiny --quiet", 2,
         ("mesh.ply", "see the back of its triangles", "invert"), setup_inverted_winding),
    Case("mesh Y up, cameras Z up", "fit {bad} --out {tmp}/out --preset tiny --quiet", 2,
         ("mesh.ply", "not where the images see the object", "turned +90 degrees about x they agree on 100.0%",
          "Y-up"), setup_y_up_mesh),
    # ---- geometry settings
    Case("geometry samples=-1", GEO + " --set samples=-1", 2, ("samples", "below 2")),
    Case("geometry mesh_resolution", GEO + " --set mesh_resolution=100000", 2, ("mesh_resolution", "above 2048")),
    Case("geometry preset typo", GEO + " --set preset=tinny", 2, ("did you mean 'tiny'?",)),
    Case("geometry --device bogus", GEO + " --device bogus", 2, ("--device bogus",)),
    Case("geometry into a fit run", "geometry {scene} --out {run} --preset tiny --quiet", 2,
         ("holds a nefii fit run, not a geometry run",)),
    # ---- refine
    Case("refine steps=0", "refine {tmp}/norun --set steps=0", 2, ("steps", "below 1")),
    Case("refine unknown setting", "refine {tmp}/norun --set stepz=3", 2, ("stepz", "did you mean 'steps'?")),
    Case("refine where no run is", "refine {tmp}/norun", 2, ("norun", "model.pt", "not found")),
    Case("refine a fit on a mesh", "refine {run}", 2, ("--geometry GEO",)),
    # ---- eval and relight flags, refused before the run is read
    Case("eval --spp -1", "eval {tmp}/norun --spp -1", 2, ("--spp", "below 1")),
    Case("eval --spp 0", "eval {tmp}/norun --spp 0", 2, ("--spp", "below 1")),
    Case("eval --seed -1", "eval {tmp}/norun --seed -1", 2, ("--seed", "below 0")),
    Case("eval --device bogus", "eval {tmp}/norun --device bogus", 2, ("--device bogus",)),
    Case("eval --threads -1", "eval {tmp}/norun --threads -1", 2, ("--threads", "below 0")),
    Case("relight --threads -2", "relight {tmp}/norun --envmap {scene}/envmap.exr --threads -2", 2,
         ("--threads", "below 0")),
    Case("relight --spp 0", "relight {tmp}/norun --envmap {scene}/envmap.exr --spp 0", 2, ("--spp",)),
    Case("relight --max-bounces 0", "relight {tmp}/norun --envmap {scene}/envmap.exr --max-bounces 0", 2,
         ("--max-bounces", "below 1")),
    Case("relight 1e6 x 1e6 cameras", "relight {run} --envmap {scene}/envmap.exr --spp 1 --quiet --cameras {bad}",
         2, ("cameras.json", "1000000x1000000", "GiB"), setup_huge_cameras),
    Case("relight under a 3e38 map", "relight {run} --envmap {bad} --spp 1 --quiet", 2,
         ("sun.exr", "overflows", "--exposure"), setup_blinding_map),
    Case("relight --out is a file", "relight {run} --envmap {scene}/envmap.exr --spp 1 --quiet --out {bad}", 2,
         ("notes.txt", "not a folder"), setup_a_file),
    Case("geometry --out is a file", "geometry {scene} --out {bad} --preset tiny --quiet", 2,
         ("notes.txt", "not a folder"), setup_a_file),
    # ---- export writes only its own files
    Case("export beside a README", "export {run} --out {bad} --texture-size 16 --quiet", 2,
         ("README.txt", "--force"), setup_export_beside_others),
]


@pytest.mark.parametrize("case", CASES, ids=[c.name for c in CASES])
def test_bad_input_is_one_line(case: Case, scene, run, tmp_path):
    bad = case.setup(scene, tmp_path) if case.setup is not None else None
    before = {p: p.read_bytes() for p in (bad.rglob("*") if bad is not None and bad.is_dir() else []) if p.is_file()}
    argv = case.argv.format(scene=scene, run=run, tmp=tmp_path, missing=tmp_path / "no_such_dataset", bad=bad)
    r = cli(argv.split())
    assert_one_line_error(r, *case.words)
    assert not (tmp_path / "out").exists(), "nothing is written on bad input"
    for p, content in before.items():
        assert p.read_bytes() == content, f"{p} was changed"


def test_export_force_replaces_and_writes_only_its_files(run, tmp_path):
    d = tmp_path / "D"
    d.mkdir()
    (d / "keep.txt").write_text("mine")
    assert cli(["export", run, "--out", d / "x.glb", "--texture-size", "16", "--quiet"]).rc == 0
    assert sorted(p.name for p in d.iterdir()) == ["README.txt", "envmap.exr", "keep.txt", "x.glb"]
    assert_one_line_error(cli(["export", run, "--out", d / "x.glb", "--texture-size", "16", "--quiet"]), "--force")
    assert cli(["export", run, "--out", d / "x.glb", "--texture-size", "16", "--quiet", "--force"]).rc == 0


# ---------------------------------------------------------------------------- warnings: legitimate, suspicious

def _fit_one_step(data: Path, out: Path, *extra: str) -> Result:
    return cli(["fit", data, "--out", out, "--preset", "tiny", "--quiet", "--set", "steps=1", "--set", "threads=1",
                *extra])


def test_a_single_channel_view_among_rgba_views_is_a_warning(scene, tmp_path):
    root = Path(shutil.copytree(scene, tmp_path / "mixed"))
    img = read_exr(root / "train" / "r_2.exr")
    write_exr(root / "train" / "r_2.exr", img[..., 0])
    r = _fit_one_step(root, tmp_path / "out")
    assert r.rc == 0, r.err
    assert len(r.warnings) == 1 and "r_2.exr" in r.warnings[0] and "no alpha channel" in r.warnings[0], r.err


def test_negative_training_pixels_are_a_warning(scene, tmp_path):
    root = Path(shutil.copytree(scene, tmp_path / "negative"))
    img = read_exr(root / "train" / "r_1.exr")
    img[0, :3, :3] = -0.5
    write_exr(root / "train" / "r_1.exr", img)
    r = _fit_one_step(root, tmp_path / "out")
    assert r.rc == 0, r.err
    assert any("r_1.exr" in w and "3 pixel(s) with negative values" in w for w in r.warnings), r.err


def test_a_mesh_far_from_every_camera_is_a_warning_and_unseen_an_error(scene, tmp_path):
    mesh = trimesh.load(scene / "mesh.ply", force="mesh", process=False)
    mesh.apply_translation((1000.0, 0.0, 0.0))
    mesh.export(tmp_path / "far.ply")
    r = _fit_one_step(scene, tmp_path / "out", "--mesh", str(tmp_path / "far.ply"))
    assert any("far.ply" in w and "nearest camera" in w for w in r.warnings), r.err
    assert_one_line_error(r, "far.ply", "the mesh is not where the images see the object")


def test_a_mesh_partly_wound_inside_out_is_a_warning(scene, tmp_path):
    """A fifth of the faces reversed: the fit runs, and says the winding is mixed (all of them reversed is an
    error: the bad-input table above)."""
    mesh = trimesh.load(scene / "mesh.ply", force="mesh", process=False)
    faces = np.array(mesh.faces)
    some = np.random.default_rng(0).random(len(faces)) < 0.2
    faces[some] = faces[some][:, ::-1]
    trimesh.Trimesh(mesh.vertices, faces, process=False).export(tmp_path / "mixed.ply")
    r = _fit_one_step(scene, tmp_path / "out", "--mesh", str(tmp_path / "mixed.ply"))
    assert r.rc == 0, r.err
    assert any("mixed.ply" in w and "back of its triangles" in w for w in r.warnings), r.err
    r = _fit_one_step(scene, tmp_path / "out2")
    assert r.rc == 0 and not any("back of its triangles" in w for w in r.warnings), r.err


def test_a_mesh_the_masks_partly_disagree_with_is_a_warning(scene, tmp_path):
    """The mesh shifted by an eighth of its diagonal: the fit runs, and says how far masks and mesh agree (the
    scene's own mesh agrees without a word, above)."""
    mesh = trimesh.load(scene / "mesh.ply", force="mesh", process=False)
    mesh.apply_translation((0.3, 0.0, 0.0))
    mesh.export(tmp_path / "shifted.ply")
    r = _fit_one_step(scene, tmp_path / "out", "--mesh", str(tmp_path / "shifted.ply"))
    assert r.rc == 0, r.err
    assert any("shifted.ply" in w and "masks and the mesh agree on 84.4%" in w for w in r.warnings), r.err
    r = _fit_one_step(scene, tmp_path / "out2")
    assert r.rc == 0 and not any("masks and the mesh agree" in w for w in r.warnings), r.err


def test_every_preset_is_valid_and_a_typo_is_named():
    from nefii.fit.config import PRESETS, resolve_config
    from nefii.sdf.config import GEOMETRY_PRESETS, resolve_geometry_config
    for p in PRESETS:
        resolve_config(p, [])
    for p in GEOMETRY_PRESETS:
        resolve_geometry_config(p, [])
    with pytest.raises(KeyError, match="did you mean 'paper'"):
        resolve_config("papr", [])
