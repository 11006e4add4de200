"""The research group's reference files (manifest, concept map, pair summary), copied into tests/fixtures/formats."""

from pathlib import Path

FORMATS = Path(__file__).resolve().parent / "fixtures" / "formats"
