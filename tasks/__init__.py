"""Prefect tasks: thin wrappers of the `steering_core` operations, one module per phase.

The machinery every task shares, a module per job: `retries` (which failures are tried again),
`cache_keys` (a run's identity from its inputs' content), `cache_records` (where a record lives and the
checks it passes before Prefect reads it), `results` (`rooted`: results under the run's output root) and
`buckets` (pulling inputs and publishing outputs around a task on a bucket root).
"""
