"""The fleet's setup: `prefect.yaml` (every deployment), and `setup` (pools, limits, automation, result storage)."""
