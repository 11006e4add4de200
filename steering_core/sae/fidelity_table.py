"""A judgement's files and its table, readable without torch: the layer report and the demo print it too."""

from __future__ import annotations

from typing import Any

FIDELITY_JSON = "fidelity.json"
FIDELITY_MD = "fidelity.md"
FIDELITY_PNG = "fidelity.png"
TABLE_HEADER = ("SAE", "rows", "FVU", "L0", "dead", "dense", "Δ_recon", "Δ_zero", "recovered")


def number(value: float | None, spec: str = ".3f") -> str:
    """Return a value as text, or a dash for none."""
    return "—" if value is None else format(value, spec)


def table_rows(record: dict[str, Any]) -> list[tuple[str, ...]]:
    """Return the table's rows (cells as strings, `TABLE_HEADER` order), one per SAE of a fidelity record."""
    out = []
    for label, entry in record["saes"].items():
        fit, change = entry["rows"], entry["actions"] or {}
        out.append((
            f"{label} ({entry['name']})", str(fit["rows"]), number(fit["fvu"]), number(fit["l0"], ".1f"),
            f"{fit['dead']} / {fit['d_sae']}", str(fit["dense"]), number(change.get("delta_recon"), ".4f"),
            number(change.get("delta_zero"), ".4f"), number(change.get("recovered")),
        ))
    return out
