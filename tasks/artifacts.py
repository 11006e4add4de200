"""Prefect artifacts: capture progress, pairwise cosine tables, per-layer reports, links to outputs.

Keys are stable (lowercase, digits, dashes), so every run adds a version to the same artifact and
the UI shows its history.
"""

from __future__ import annotations

import re
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from prefect.artifacts import (
    create_link_artifact,
    create_markdown_artifact,
    create_progress_artifact,
    create_table_artifact,
    update_progress_artifact,
)

from steering_core.fileio import read_json
from steering_core.layout import SUMMARY_JSON, SUMMARY_MD

PROGRESS_EVERY_SECONDS = 5.0  # API calls are cheap but not free: update at most this often (and at the end)


def artifact_key(*parts: Any) -> str:
    """Return a Prefect artifact key from parts: lowercase, runs of other characters become one dash."""
    text = "-".join(str(part) for part in parts).lower()
    return re.sub(r"[^a-z0-9]+", "-", text).strip("-")


def progress_artifact(key: str, unit: str, description: str) -> Callable[[int, int], None]:
    """Create a progress artifact at 0% and return a `progress(done, total)` callback that updates it."""
    artifact_id = create_progress_artifact(0.0, key=key, description=description)
    last = 0.0

    def update(done: int, total: int) -> None:
        nonlocal last
        now = time.monotonic()
        if done < total and now - last < PROGRESS_EVERY_SECONDS:
            return
        last = now
        percent = 100.0 * done / total if total else 100.0
        update_progress_artifact(artifact_id, percent, description=f"{description}: {done}/{total} {unit}")

    return update


def publish_layer_report(layer_path: Path, flow_key: str) -> None:
    """Publish one layer's report: summary.md as markdown, pairwise cosines as a table, links to files."""
    layer = layer_path.name
    summary = read_json(layer_path / SUMMARY_JSON)
    create_markdown_artifact(
        (layer_path / SUMMARY_MD).read_text(encoding="utf-8"),
        key=artifact_key(flow_key, "report", layer),
        description=f"Steering report for {layer} ({layer_path})",
    )
    rows = [{"pairs": name, **{k: round(v, 6) if isinstance(v, float) else v for k, v in entry.items()}}
            for name, entry in summary["pairwise"].items()]
    if rows:
        create_table_artifact(
            rows, key=artifact_key(flow_key, "pairwise-cosines", layer),
            description=f"Cosines and norms between every two pairs' directions, {layer}",
        )
    links = {"summary-md": layer_path / SUMMARY_MD, "summary-json": layer_path / SUMMARY_JSON}
    links |= {f"plot-{name}": layer_path / file for name, file in summary["plots"].items()}
    for name, path in links.items():
        create_link_artifact(
            Path(path).resolve().as_uri(), link_text=Path(path).name,
            key=artifact_key(flow_key, layer, name), description=f"{layer}: {name}",
        )
