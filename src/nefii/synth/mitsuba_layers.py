"""A Mitsuba integrator that splits the first bounce into its specular and diffuse lobes.

``L_spec(x, w_o)`` is the radiance reflected towards the camera by the *specular lobe alone*
at the first hit, with full light transport (every lobe, every bounce) behind it; the
diffuse layer is the rest, ``L_diff = L - L_spec``. Setting the base colour to 0 everywhere
does not give ``L_spec`` (it also darkens everything the specular lobe reflects, ~3x too
dark); here only the first-hit BSDF is swapped, for a twin principled BSDF whose base colour
is 0 (with metallic 0 and no tint, the principled specular lobe does not depend on it).

Estimator at the first hit ``x`` (paper notation: ``beta`` throughput, ``w_i`` light direction):

* emitter sampling: ``f(w_i) cos / p_light * L_e * w_mis(p_light, p_bsdf)``;
* BSDF sampling with the *full* BSDF's sampler: ``f(w_i) cos / p_bsdf`` times either
  ``L_e * w_mis(p_bsdf, p_light)`` when the ray escapes, or Mitsuba's own ``path`` integrator
  estimate of ``L_i`` from the next hit (it does its own emitter sampling and MIS there);
* both lobes share the samples: ``f`` is the twin's value for ``L_spec`` and the full BSDF's
  for ``L``, so ``L_spec + L_diff = L`` exactly and ``L`` can be checked against ``path``.

Also returned, per pixel, as AOVs averaged over the pixel (background 0): the full ``L``,
base colour, roughness (the BSDF's own texture), world shading normal and world position.
Not supported: area emitters on the first hit (there are none), volumes, delta light lobes
(the principled BSDF has none).
"""
from __future__ import annotations

AOV_NAMES = ("full.R", "full.G", "full.B", "albedo.R", "albedo.G", "albedo.B", "roughness.Y",
             "normal.X", "normal.Y", "normal.Z", "position.X", "position.Y", "position.Z")
"""channels after R, G, B (the specular layer) and A in the rendered tensor"""

_CLASSES: dict[str, type] = {}


def layer_integrator(mi, dr, max_depth: int, spec_bsdf, roughness):
    """An instance for the current variant; ``spec_bsdf`` is the twin BSDF, ``roughness`` its texture."""
    cls = _CLASSES.get(mi.variant())
    if cls is None:
        cls = _CLASSES[mi.variant()] = _define(mi, dr)
    integrator = cls(mi.Properties())
    integrator.configure(max_depth, spec_bsdf, roughness)
    return integrator


def _define(mi, dr) -> type:
    def mis_weight(pdf_a, pdf_b):
        """Power heuristic, 0 where undefined."""
        a2, b2 = dr.square(pdf_a), dr.square(pdf_b)
        w = a2 / dr.maximum(a2 + b2, 1e-30)  # a guard, not 1/0: scalar variants raise on it
        return dr.select(dr.isfinite(w), w, 0.0)

    class SpecularLayerIntegrator(mi.SamplingIntegrator):
        def configure(self, max_depth: int, spec_bsdf, roughness) -> None:
            self.spec_bsdf = spec_bsdf
            self.roughness = roughness
            self.nested = mi.load_dict({"type": "path", "max_depth": max_depth - 1})
            self.scalar = mi.variant().startswith("scalar")
            """one ray per call, Python control flow; else whole wavefronts with masks"""

        def aov_names(self):
            return list(AOV_NAMES)

        def sample(self, scene, sampler, ray, medium=None, active=True):
            ctx = mi.BSDFContext()
            si = scene.ray_intersect(mi.Ray3f(ray), active)
            hit = mi.Bool(active) & si.is_valid()
            if self.scalar and not hit:  # scalar variants: one ray, and no BSDF to ask on a miss
                return mi.Spectrum(0.0), False, [0.0] * len(AOV_NAMES)
            bsdf = si.bsdf(ray)
            L_spec, L = mi.Spectrum(0.0), mi.Spectrum(0.0)

            # ---------------- emitter sampling at the first hit
            ds, em_weight = scene.sample_emitter_direction(si, sampler.next_2d(hit), True, hit)
            active_em = hit & (ds.pdf != 0.0)
            wo = si.to_local(ds.d)
            f_full, pdf_bsdf = bsdf.eval_pdf(ctx, si, wo, active_em)
            f_spec = self.spec_bsdf.eval(ctx, si, wo, active_em)
            w_em = dr.select(ds.delta, 1.0, mis_weight(ds.pdf, pdf_bsdf))
            L += dr.select(active_em, f_full * em_weight * w_em, 0.0)
            L_spec += dr.select(active_em, f_spec * em_weight * w_em, 0.0)

            # ---------------- BSDF sampling (full BSDF) at the first hit
            bs, weight_full = bsdf.sample(ctx, si, sampler.next_1d(hit), sampler.next_2d(hit), hit)
            active_b = hit & (bs.pdf > 0.0)
            weight_spec = self.spec_bsdf.eval(ctx, si, bs.wo, active_b) / dr.select(active_b, bs.pdf, 1.0)
            ray2 = si.spawn_ray(si.to_world(bs.wo))
            si2 = scene.ray_intersect(ray2, active_b)

            # escaped: environment light, MIS against emitter sampling
            escaped = active_b & dr.select(si2.is_valid(), False, True)  # not '~': a bool in scalar variants
            if not self.scalar or escaped:  # scalar variants would dereference a null emitter
                ds2 = mi.DirectionSample3f(scene, si2, si)
                pdf_em = scene.pdf_emitter_direction(si, ds2, escaped)
                delta = mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta)
                Le = si2.emitter(scene).eval(si2, escaped) * dr.select(delta, 1.0, mis_weight(bs.pdf, pdf_em))
                L += dr.select(escaped, weight_full * Le, 0.0)
                L_spec += dr.select(escaped, weight_spec * Le, 0.0)

            # hit a surface: full transport from there by Mitsuba's path tracer
            onward = active_b & si2.is_valid()
            if not self.scalar or onward:
                Li, _, _ = self.nested.sample(scene, sampler, ray2, None, onward)
                L += dr.select(onward, weight_full * Li, 0.0)
                L_spec += dr.select(onward, weight_spec * Li, 0.0)

            # ---------------- per-pixel ground truth of the first hit
            albedo = bsdf.eval_diffuse_reflectance(si, hit)
            rough = self.roughness.eval_1(si, hit)
            n, p = si.sh_frame.n, si.p
            aovs = [L[0], L[1], L[2], albedo[0], albedo[1], albedo[2], rough, n[0], n[1], n[2], p[0], p[1], p[2]]
            return L_spec, hit, [dr.select(hit, a, 0.0) for a in aovs]

    return SpecularLayerIntegrator
