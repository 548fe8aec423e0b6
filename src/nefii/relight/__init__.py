"""Relighting a fitted object under a new environment by multi-bounce path tracing (``nefii relight``).

environment            an equirectangular HDR file as light: reading, --rotate, --exposure, sampling
bsdf                   the BRDF's evaluation and its one-direction cosine + GGX mixture sampler
pathtracer             the path tracer: emitter and BSDF sampling with MIS, Russian roulette
pathtracer_reference   its simple sibling (cosine sampling only), for tests
render                 a camera view: jittered paths per pixel, chunked
cameras                the cameras to render (test split or a transforms.json)
sets                   what one output folder holds: views, each view's light, the truth to score against
scoring                albedo scale, PSNR/SSIM, metrics.json, the PNG tone curve
"""
