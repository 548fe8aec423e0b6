"""Rendering math of nefii: pure functions over tensors, no parameters, any device.

frame      vectors and local shading frames
equirect   the direction <-> equirectangular pixel mapping (docs/design.md)
sg         spherical Gaussians and mixtures
brdf       the simplified Disney BRDF (Lambert + GGX/Schlick/Smith-Schlick)
samplers   cosine, GGX visible-normal and SG-mixture samplers with their pdfs
mis        power-heuristic weights
estimator  the MIS Monte Carlo estimator of Eq. 2 (and estimator_reference, cosine only)
"""
