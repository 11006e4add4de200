"""Latent steering for pi0.5: LIBERO demos -> residual captures -> SAE steering vectors.

A plain library (no Prefect): one module per pipeline step. `tasks/` and `flows/`
wrap these functions for Prefect; the `latent-steering` CLI calls them directly.
"""
