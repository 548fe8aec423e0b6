"""From a fitted run to an asset other tools open (see ``design.md``).

unwrap   UV atlas of the frozen mesh (xatlas), sized for a square texture
bake     texel -> surface point rasterisation, the material decoded there, push-pull dilation
asset    the Y-up GLB / OBJ+MTL writers, the environment map and the Blender README
three    the pinned three.js release from the npm registry, found in a cache or fetched once
viewer   ``nefii view``'s self-contained HTML page
"""
