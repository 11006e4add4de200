"""Benchmarks: each phase against the seed's approach, measured in the same process. See BENCHMARKS.md."""
