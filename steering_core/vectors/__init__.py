"""Steering vectors, the project's main product: per-concept SAE statistics, per-pair directions, their report.

Modules: `concept_stats` (streaming statistics of one concept's residuals through an SAE), `directions` (a pair's
`positive - negative` latent mean, decoded to residual space; pairwise cosines), `pair_slices` (a pair's two
slice files against their index.json), `pair_order` (which concept of a pair is positive), `report` (the
per-layer steering report).
"""
