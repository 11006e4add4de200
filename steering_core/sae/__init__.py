"""The SAE itself: its files, named releases, encode/decode, and training one on π0.5's residuals.

Modules: `formats` (cfg.json and weights on disk), `registry` (named releases), `model` (encode/decode),
`fidelity_table` (a judgement's files and table, readable without torch), `training/` (SAELens training,
held-out episodes). Steering vectors built with an SAE: `steering_core.vectors`; judging SAEs:
`steering_core.sae_quality`.
"""

from steering_core.sae.model import Sae, load_sae

__all__ = ["Sae", "load_sae"]
