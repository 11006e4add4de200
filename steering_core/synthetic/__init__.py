"""Generators of small, real-format inputs: LIBERO demos, a pi0.5 checkpoint, a tokenizer, an SAE.

Used by the tests and by `latent-steering demo`; real dimensions stay the library defaults.
"""
