"""Phase 3, SAE: SAE formats and registry, encode/decode, per-concept statistics, steering vectors, report.

Modules: `formats` (cfg.json and weights on disk), `registry` (named releases), `model` (encode/decode),
`concept_stats` (streaming statistics of one concept), `steering` (pair directions), `report`.
"""

from steering_core.sae.model import Sae, load_sae

__all__ = ["Sae", "load_sae"]
