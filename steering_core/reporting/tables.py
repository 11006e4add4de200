"""Plain-text tables for the terminal: columns aligned by padding, no trailing spaces."""

from __future__ import annotations

from collections.abc import Sequence


def text_table(header: Sequence[str], rows: Sequence[Sequence[str]]) -> str:
    """Return `header` and `rows` (strings, one per column) as left-aligned columns two spaces apart."""
    lines = [tuple(header), *map(tuple, rows)]
    if any(len(line) != len(header) for line in lines):
        raise ValueError(f"every row needs {len(header)} cells (the header's {', '.join(header)})")
    widths = [max(len(line[i]) for line in lines) for i in range(len(header))]
    return "\n".join("  ".join(cell.ljust(width) for cell, width in zip(line, widths, strict=True)).rstrip()
                     for line in lines)
