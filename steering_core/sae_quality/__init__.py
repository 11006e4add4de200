"""Judging and browsing SAEs: how well they reconstruct held-out rows and keep π0.5's actions, what their features
respond to.

Modules: `fidelity` (FVU, L0, dead and dense latents), `action_fidelity` (actions with residuals replaced by the
SAE's reconstruction), `fidelity_report` and `judge_run` (a layer's judgement, as the pipeline writes it),
`feature_scan`, `feature_run` and `feature_page` (what each latent responds to; one HTML page per layer),
`neuronpedia` (the export for Neuronpedia's tooling).
"""
