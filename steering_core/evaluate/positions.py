"""R and the mean-difference directions must come from rows at the positions the evaluation steers.

The language model is steered at each instruction token, the action expert at each action token: the
slices must hold one row per such token (`token_type: instructions` or `decision`, `reduce: token`), as
their folder's index.json records. Frame means (`--reduce frame`) or other tokens (`prompt`, `last`)
give another R and another direction than the ones steered, so the run is refused.
"""

from __future__ import annotations

from pathlib import Path

from steering_core.layout import SLICE_INDEX_FILE
from steering_core.storage.fileio import read_json

STEERED_TOKENS = {"lm": "instructions", "expert": "decision"}


def check_positions(slices: tuple[Path, ...], stream: str) -> str | None:
    """Raise ValueError for slices cut at other positions than the steered ones; return a note for slices
    without an index.json (positions unchecked), else None."""
    unchecked = []
    for path in slices:
        index_path = path.parent / SLICE_INDEX_FILE
        if not index_path.is_file():
            unchecked.append(str(path))
            continue
        index = read_json(index_path)
        token_type = index.get("token_selection", {}).get("token_type", index.get("settings", {}).get("token_type"))
        reduce = index.get("settings", {}).get("reduce", "token")
        wanted = STEERED_TOKENS[stream]
        if token_type != wanted or reduce != "token":
            raise ValueError(
                f"{index_path}: token_type {token_type!r}, reduce {reduce!r}; the evaluation steers each "
                f"`{wanted}` token, so R and the directions must come from per-token `{wanted}` rows "
                f"(slice with --token-type {wanted} --reduce token)")
    if unchecked:
        return f"slices without {SLICE_INDEX_FILE} ({', '.join(unchecked)}): their token positions are not checked"
    return None
