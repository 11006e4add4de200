"""Where the research group's reference files live: `shared/` beside the repository checkout."""

from pathlib import Path

FORMATS = Path(__file__).resolve().parents[2] / "shared" / "reference" / "formats"
