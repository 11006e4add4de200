"""Closed-loop rollouts of a (steered) policy in the LIBERO simulator, following openpi's LIBERO client.

`assets` verifies the scene assets, `libero_env` builds environments, `protocol` holds openpi's constants and
preprocessing, `predicates` evaluates task goals on any scene holding their objects, `episode` runs one episode;
`grid`, `plan` and `run` lay out and run the steering experiment's cells, `records`, `stats`, `plots`, `video`
and `report` write what they found. Modules import the simulator lazily: importing this package is cheap.
"""
