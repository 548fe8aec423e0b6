"""The learnable parts: encodings, the material field M, the radiance cache L, the SG environment E.

Networks map inputs to quantities; all rendering math stays in :mod:`nefii.render`.
"""
