"""Built-in ground-truth scenes rendered by Mitsuba 3 (``nefii synth``).

noise            deterministic tileable fractal noise (textures and skies)
meshes           procedural triangle meshes (revolutions, tori, boxes), PLY output
textures         procedural material patterns and the per-scene texture atlas
skies            procedural HDR environments (sun disc, sky, clouds, ground, horizon; a room)
envmaps          baking an environment onto a lat-long grid with the sun integrated per texel
scenes           the built-in scenes by name; ``smallest_scene()`` for ``nefii demo``
cameras          camera rigs on a band of a sphere, NeRF-synthetic transforms json
mitsuba_backend  everything that touches Mitsuba: variant, env-map grid, scene, render passes
mitsuba_layers   the integrator that splits the first bounce into specular and diffuse layers
layout           writing the output folder (docs/datasets.md)
generate         ``synthesize(settings, out)``: the whole run, written atomically

Only ``mitsuba_backend`` and ``mitsuba_layers`` import mitsuba, and only when rendering.
"""
from .scenes import SCENES, scene_names, smallest_scene

__all__ = ["SCENES", "scene_names", "smallest_scene"]
