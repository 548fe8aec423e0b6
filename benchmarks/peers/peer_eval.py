"""Score the peer's recovered scene with nefii's eval protocol (``nefii eval``'s Table 1 code).

* Albedo and roughness: its textures at the test views' pixel-centre hits (``views``), the way
  ``nefii eval`` reads nefii's material field at the same hits.
* Novel-view colour and the specular layer: Mitsuba renders the recovered scene (textures and
  env map) from the test cameras with the integrator that made the ground truth
  (``nefii.synth.mitsuba_layers``: path tracing to depth 12, the specular lobe's share of the
  first bounce kept apart), un-premultiplied by its coverage as the ground-truth maps are.

Both go through ``nefii.evaluate.table1.view_scores`` / ``mean_scores`` and ``write_metrics``.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from nefii.data.scene import SceneData
from nefii.evaluate.report import tonemap_display, write_grid, write_metrics
from nefii.evaluate.table1 import ViewArrays, mean_scores, view_scores
from nefii.io.atomic import atomic_dir
from nefii.io.exr import write_exr
from nefii.synth.layout import straight
from nefii.synth.meshes import TriMesh
from nefii.synth.mitsuba_backend import MitsubaRenderer
from nefii.synth.textures import Atlas

from mitsuba_peer import MeshData, PeerFit, camera_rig
from views import TestViews, textures_at_views

RENDER_DEPTH = 12
"""path length of the novel-view renders: what the ground truth was rendered with"""


def recovered_atlas(mesh: MeshData, fit: PeerFit) -> Atlas:
    """The recovered scene as the synth renderer takes it (mesh split at the atlas seams)."""
    a = mesh.atlas
    tri = TriMesh(mesh.vertices[a.source], a.faces, mesh.normals[a.source], a.uv)
    return Atlas(tri, fit.base_color, fit.roughness, ("object",), (len(a.faces),))


def evaluate(test: SceneData, views: TestViews, uvs: list[np.ndarray], mesh: MeshData, fit: PeerFit,
             out: Path, spp: int, seed: int = 0, threads: int = 1) -> dict:
    """Render and score every test view; writes ``out`` (metrics.json/md, EXRs, grids) atomically."""
    cams = camera_rig(test)
    renderer = MitsubaRenderer(recovered_atlas(mesh, fit), {"recovered": fit.envmap}, cams.width, cams.height,
                               cams.fov_x_deg, RENDER_DEPTH)
    renderer.dr.set_thread_count(threads)  # the renderer sizes Dr.Jit's pool from $OMP_NUM_THREADS
    albedo, rough = textures_at_views(views, uvs, fit.base_color, fit.roughness)
    per_view = []
    with atomic_dir(out) as tmp:
        for v in range(len(test)):
            renderer.set_camera(cams.c2w_gl[v])
            layers = renderer.render_layers("recovered", spp, seed * 1000 + v)
            a = layers["alpha"]
            pred = ViewArrays(straight(layers["full"], a), albedo[v], rough[v], straight(layers["specular"], a))
            gt = views.gt[v]
            scores, scale = view_scores(pred, gt, views.masks[v])
            k = test.indices[v]
            per_view.append({"index": k, "name": test.names[v], "albedo_scale": [float(s) for s in scale], **scores})
            for name, arr in (("rgb", pred.rgb), ("specular", pred.specular), ("albedo", pred.albedo),
                              ("roughness", pred.roughness)):
                write_exr(tmp / f"{k}_{name}.exr", arr)
            rows = [(tonemap_display(gt.rgb), tonemap_display(pred.rgb))]
            flags = [False]
            if gt.albedo is not None:
                rows.append((gt.albedo, pred.albedo * scale))
                flags.append(True)
            if gt.roughness is not None:
                rows.append((gt.roughness, pred.roughness))
                flags.append(False)
            write_grid(tmp / f"{k}_grid.png", rows, flags)
        means = mean_scores(per_view)
        notes = {"system": "Mitsuba 3 prb peer (benchmarks/peers/mitsuba_inverse.py)",
                 "albedo": "textures at the pixel-centre hits; aligned per view and channel by median(gt/pred) "
                           "over the mask, linear; scored in sRGB",
                 "rgb": f"Mitsuba path tracing of the recovered scene, depth {RENDER_DEPTH}, {spp} spp, "
                        "un-premultiplied by coverage",
                 "views": f"{len(per_view)} test views from {test.root}"}
        write_metrics(tmp, means, per_view, notes)
    return means
