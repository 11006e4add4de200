"""The directions compared by the evaluation, all in the residual space of one layer of one stream.

Language model (layer L): every method phase 3 wrote for the pair (`steering_core.vectors.methods`: `sae`,
`mean_difference`, `sae_top_k`, `probe`, `sae_effect`, `file`), each a unit direction with its clamp levels.
Action expert (expert layer K, from the pair's `decision` slices, `evaluate.expert_layers`): `mean_difference`,
mean(positive decision rows) − mean(negative decision rows).

Each direction is evaluated in every mode of `evaluate.modes`: an entry is named `<method>` (add) or
`<method>:clamp`. The null directions (`random_NN`, `permuted_NN`, add mode) come from
`steering_core.evaluate.nulls`.
"""

from __future__ import annotations

from pathlib import Path

import torch

from steering_core.layout import PAIR_SUMMARY_FILE
from steering_core.pairs import SIDES
from steering_core.storage.fileio import read_json
from steering_core.vectors.methods.direction_file import MethodDirection, read_method_direction, unit_direction
from steering_core.vectors.slice_rows import read_slice_rows

MODES = ("add", "clamp")
RANDOM = "random_{index:02d}"
PERMUTED = "permuted_{index:02d}"
NULL_PREFIXES = ("random_", "permuted_")


def is_null(name: str) -> bool:
    """Return True for a null direction's name (random or permuted)."""
    return name.startswith(NULL_PREFIXES)


def entry_name(method: str, mode: str) -> str:
    """Return the evaluation's name of a method in a mode: `probe` (add) or `probe:clamp`."""
    return method if mode == "add" else f"{method}:{mode}"


def entry_parts(name: str) -> tuple[str, str]:
    """Return (method, mode) of an entry name (`entry_name`'s inverse)."""
    method, _, mode = name.partition(":")
    return method, mode or "add"


def pair_directions(pair_path: Path, methods: tuple[str, ...] | None = None) -> dict[str, MethodDirection]:
    """Return method -> unit direction of one pair folder of phase 3 (`methods`: those only, in that order).

    ValueError naming the folder when phase 3 wrote no methods (outputs older than the registry) or lacks one
    of `methods`.
    """
    summary = read_json(pair_path / PAIR_SUMMARY_FILE)
    written = summary.get("methods") if isinstance(summary, dict) else None
    if not written:
        raise ValueError(f"{pair_path / PAIR_SUMMARY_FILE}: lists no direction methods (written before "
                         "steering.methods existed); re-run the steer step")
    missing = [name for name in methods or () if name not in written]
    if missing:
        raise ValueError(f"{pair_path}: evaluate.methods {list(methods)}: phase 3 wrote no {missing} (it wrote "
                         f"{list(written)}); add them to steering.methods and re-run steer")
    return {name: read_method_direction(pair_path / written[name]["file"]) for name in methods or written}


def decision_directions(slices: tuple[Path, Path], pair: str, layer: int) -> dict[str, MethodDirection]:
    """Return the action expert's `mean_difference` of one pair at expert layer `layer`: the difference of the
    (positive, negative) `decision` slices' row means (training episodes only, float64), with their levels."""
    means = dict(zip(SIDES, (read_slice_rows(path).double().mean(0) for path in slices), strict=True))
    unit, norm = unit_direction(means["positive"] - means["negative"],
                                f"pair {pair!r}, expert layer {layer}, decision slices {slices[0].parent}")
    levels = (float(means["negative"] @ unit.double()), float(means["positive"] @ unit.double()))
    return {"mean_difference": MethodDirection("mean_difference", pair, layer, unit, norm, levels, None, {})}


def check_width(directions: dict[str, torch.Tensor], width: int, where: str, stream: str = "lm") -> None:
    """Raise ValueError naming every direction whose shape is not (width,) (the width of `stream`)."""
    wrong = {name: tuple(v.shape) for name, v in directions.items() if tuple(v.shape) != (width,)}
    if wrong:
        what = "action expert's" if stream == "expert" else "language model's"
        raise ValueError(f"{where}: directions {wrong} do not match the policy's {what} residual width ({width},); "
                         "use vectors of the same model and layer")
