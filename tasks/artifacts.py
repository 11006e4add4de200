"""Prefect artifacts: progress of the long steps (convert, capture, slicing, SAE statistics), per-layer reports.

Keys are stable (lowercase, digits, dashes), so every run adds a version to the same artifact and
the UI shows its history.
"""

from __future__ import annotations

import base64
import re
import socket
import time
from pathlib import Path
from typing import Any

from prefect.artifacts import (
    create_markdown_artifact,
    create_progress_artifact,
    create_table_artifact,
    update_progress_artifact,
)

from steering_core.layout import SUMMARY_JSON, SUMMARY_MD
from steering_core.storage.fileio import read_json

PROGRESS_EVERY_SECONDS = 5.0  # API calls are cheap but not free: update at most this often (and at the end)


def artifact_key(*parts: Any) -> str:
    """Return a Prefect artifact key from parts: lowercase, runs of other characters become one dash."""
    text = "-".join(str(part) for part in parts).lower()
    return re.sub(r"[^a-z0-9]+", "-", text).strip("-")


class ProgressArtifact:
    """A Prefect progress artifact kept up to date by `progress(done, total)` calls (at most every few seconds)."""

    def __init__(self, key: str, unit: str, description: str) -> None:
        self.unit, self.description = unit, description
        self.id = create_progress_artifact(0.0, key=key, description=description)
        self._last, self._percent = 0.0, 0.0

    def __call__(self, done: int, total: int, text: str | None = None) -> None:
        """Show `done` of `total` (and `text`, e.g. a `Progress.describe()` with the rate and the time left)."""
        now = time.monotonic()
        if done < total and now - self._last < PROGRESS_EVERY_SECONDS:
            return
        self._last = now
        self._percent = 100.0 * done / total if total else 100.0
        update_progress_artifact(self.id, self._percent,
                                 description=f"{self.description}: {text or f'{done}/{total} {self.unit}'}")

    def finish(self) -> None:
        """Show 100% when the step ended without counting (its outputs were already current)."""
        if self._percent < 100.0:
            self._percent = 100.0
            update_progress_artifact(self.id, 100.0, description=f"{self.description}: already up to date")


def publish_layer_report(layer_path: Path, flow_key: str) -> None:
    """Publish one layer's report for the Prefect UI: summary.md with its plots inline, and the cosines as a table.

    summary.md on disk links its plots by relative path, which the UI cannot follow; the artifact carries
    each PNG as a data URI instead, and ends with where the files are (on the machine that wrote them).
    """
    layer = layer_path.name
    summary = read_json(layer_path / SUMMARY_JSON)
    create_markdown_artifact(
        ui_report(layer_path, summary),
        key=artifact_key(flow_key, "report", layer),
        description=f"Steering report for {layer} ({layer_path})",
    )
    rows = [{"pairs": name.replace("__", " vs "), **{k: round(v, 6) if isinstance(v, float) else v
                                                   for k, v in entry.items()}}
            for name, entry in summary["pairwise"].items()]
    if rows:
        create_table_artifact(
            rows, key=artifact_key(flow_key, "pairwise-cosines", layer),
            description=f"Cosines and norms between every two pairs' directions, {layer}",
        )


def ui_report(layer_path: Path, summary: dict[str, Any]) -> str:
    """Return summary.md with every plot inlined as a PNG data URI (the trained SAE's judgement too), followed by
    the files' paths and host."""
    trained = [summary["trained_sae"]["plot"]] if summary.get("trained_sae") else []
    return ui_markdown(layer_path, [*summary["plots"].values(), *trained], [SUMMARY_MD, SUMMARY_JSON])


def ui_markdown(folder: Path, images: list[str], files: list[str]) -> str:
    """Return `folder`'s summary.md with each of `images` (paths relative to it, as the file links them) inlined as
    a PNG data URI, followed by where `files` and the images are (on the machine that wrote them)."""
    text = (folder / SUMMARY_MD).read_text(encoding="utf-8")
    for file in images:
        encoded = base64.b64encode((folder / file).read_bytes()).decode("ascii")
        text = text.replace(f"]({file})", f"](data:image/png;base64,{encoded})")
    return text.rstrip() + "\n\n## Files\n\n" + f"On `{socket.gethostname()}`, in `{folder}`:\n\n" + "\n".join(
        f"- `{name}`" for name in [*files, *images]) + "\n"
