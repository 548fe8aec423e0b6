"""Score the peer's recovered scene with ``nefii eval``'s own loop (``nefii.evaluate.run``).

* Albedo and roughness: its textures at the test views' sub-pixel hits (``views``), averaged per pixel, as
  ``nefii eval`` reads nefii's material field.
* Novel-view colour and the specular layer: Mitsuba renders the recovered scene (textures and env map) from
  the test cameras with the integrator that made the ground truth (``nefii.synth.mitsuba_layers``, path
  tracing to depth 12), un-premultiplied by its coverage as the ground-truth maps are.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from nefii.data.scene import SceneData
from nefii.evaluate.run import finish_metrics, score_and_write_view
from nefii.evaluate.table1 import ViewArrays
from nefii.io.atomic import atomic_dir
from nefii.synth.layout import straight
from nefii.synth.meshes import TriMesh
from nefii.synth.mitsuba_backend import MitsubaRenderer
from nefii.synth.textures import Atlas

from .mitsuba_peer import PeerFit, camera_rig, textures_at_hits
from .hits import TestViews

RENDER_DEPTH = 12
"""path length of the novel-view renders: what the ground truth was rendered with"""


def evaluate(test: SceneData, views: TestViews, uvs: list[np.ndarray], mesh: TriMesh, fit: PeerFit,
             out: Path, spp: int, seed: int = 0, threads: int = 1) -> dict:
    """Render and score every test view; writes ``out`` (metrics.json/md, EXRs, grids) atomically."""
    cams = camera_rig(test)
    atlas = Atlas(mesh, fit.base_color, fit.roughness, ("object",), (len(mesh.faces),))
    renderer = MitsubaRenderer(atlas, {"recovered": fit.envmap}, cams.width, cams.height, cams.fov_x_deg,
                               RENDER_DEPTH)
    renderer.dr.set_thread_count(threads)  # the renderer sizes Dr.Jit's pool from $OMP_NUM_THREADS
    albedo, rough = textures_at_hits(renderer.mi, views, uvs, fit.base_color, fit.roughness)
    with atomic_dir(out) as tmp:
        scores = []
        for v in range(len(test)):
            renderer.set_camera(cams.c2w_gl[v])
            layers = renderer.render_layers("recovered", spp, seed * 1000 + v)
            a = layers["alpha"]
            pred = ViewArrays(straight(layers["full"], a), albedo[v], rough[v], straight(layers["specular"], a))
            scores.append(score_and_write_view(tmp, test.indices[v], test.names[v], pred, views.gt[v],
                                               views.masks[v]))
        notes = {"system": "Mitsuba 3 prb peer (benchmarks.peers.mitsuba_inverse)",
                 "albedo": "textures at 4 x 4 sub-pixel hits averaged per pixel; aligned per view and channel by median(gt/pred) "
                           "over the mask, linear; scored in sRGB",
                 "rgb": f"Mitsuba path tracing of the recovered scene, depth {RENDER_DEPTH}, {spp} spp, "
                        "un-premultiplied by coverage",
                 "views": f"{len(scores)} test views from {test.root}"}
        return finish_metrics(tmp, scores, notes)
