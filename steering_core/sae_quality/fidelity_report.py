"""Judge a layer's trained SAE beside the borrowed one: fidelity.json, a fidelity.md table and a fidelity.png plot.

Both SAEs read the same held-out rows (FVU, L0, dead and dense latents: `fidelity.row_fidelity`) and, when a
policy is given, are spliced into the same frames with the same noise (Δ_recon, Δ_zero, recovered:
`action_fidelity.action_fidelity`). The verdict names the SAE with the lower FVU.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from steering_core.evaluate.frames import EvalFrame
from steering_core.evaluate.sweep import Prompts
from steering_core.reporting.plots import figure, save_png
from steering_core.reporting.progress import ProgressCallback
from steering_core.sae.fidelity_table import FIDELITY_JSON, FIDELITY_MD, FIDELITY_PNG, TABLE_HEADER, number, table_rows
from steering_core.sae.model import Sae
from steering_core.sae_quality.action_fidelity import (
    ActionFidelity,
    FrameLoader,
    SplicePolicy,
    action_fidelity,
    sae_reconstruction,
)
from steering_core.sae_quality.fidelity import DENSE_FRACTION, HISTOGRAM_EDGES, RowBatches, RowFidelity, row_fidelity
from steering_core.storage.fileio import read_json, write_json, write_text

logger = logging.getLogger(__name__)

FORMAT_VERSION = 1


@dataclass(frozen=True)
class ActionInputs:
    """What the action-change measurement reads: the policy, held-out frames, their cameras and prompts.

    `load(frames)` -> {"images", "image_masks"} (e.g. `evaluate.frames.load_frames` bound to the dataset);
    `prompts` gives each frame's tokenised prompt under its side's task (`evaluate.run.PolicyPrompts`).
    """

    policy: SplicePolicy
    frames: Sequence[EvalFrame]
    load: FrameLoader
    prompts: Prompts
    seed: int = 0
    num_steps: int = 10
    batch_size: int = 8


def judge_layer(
    out_dir: Path,
    layer: int,
    trained: Sae,
    rows: RowBatches,
    *,
    borrowed: Sae | None = None,
    actions: ActionInputs | None = None,
    progress: ProgressCallback | None = None,
    identity: str | None = None,
) -> Path:
    """Write out_dir/{fidelity.json, fidelity.md, fidelity.png} judging `trained` (and `borrowed`) at `layer`.

    `rows`: the layer's held-out rows, (b, d_in) float batches or (rows, columns) pairs, or a function
    returning them (`lambda: RowSource(run, layer, episodes=held_out).sequential(4096)`); read once.
    `actions`: the policy and held-out frames for the action change (language-model layers only); None skips
    it (its columns stay empty). `progress` counts policy calls. `identity` (a digest of everything judged:
    SAEs, rows, frames, checkpoint) is recorded; a folder already recording it is kept as it is. Returns `out_dir`.
    """
    if identity is not None and judged_identity(out_dir) == identity:
        logger.info("layer %d: %s already holds this judgement; reused", layer, out_dir)
        return out_dir
    saes = {"trained": trained} | ({"borrowed": borrowed} if borrowed is not None else {})
    fidelity = row_fidelity(saes, rows, where=f"held-out rows of layer {layer}")
    changes: dict[str, ActionFidelity] = {}
    if actions is not None:
        changes = action_fidelity(
            actions.policy, layer, {name: sae_reconstruction(sae) for name, sae in saes.items()}, actions.frames,
            actions.load, actions.prompts, seed=actions.seed, num_steps=actions.num_steps,
            batch_size=actions.batch_size, progress=progress,
        )
    record = {
        "format_version": FORMAT_VERSION,
        "identity": identity,
        "layer": layer,
        "verdict": verdict(fidelity, changes),
        "dense_fraction": DENSE_FRACTION,
        "histogram_log10_edges": list(HISTOGRAM_EDGES),
        "saes": {
            name: {
                "name": sae.name,
                "architecture": sae.cfg.architecture,
                "d_in": sae.cfg.d_in,
                "weights_sha256": sae.weights_sha256,
                "rows": fidelity[name].as_json(),
                "actions": changes[name].as_json() if name in changes else None,
            }
            for name, sae in saes.items()
        },
        "actions": None if actions is None else {
            "seed": actions.seed, "num_steps": actions.num_steps, "positions": "instruction tokens",
            "frames": [frame.as_json() for frame in actions.frames],
        },
    }
    plot_fidelity(out_dir / FIDELITY_PNG, record)
    write_text(out_dir / FIDELITY_MD, fidelity_markdown(record))
    write_json(out_dir / FIDELITY_JSON, record)  # last: its presence means the folder is complete
    logger.info("layer %d: %s (%s)", layer, record["verdict"], out_dir)
    return out_dir


def judged_identity(out_dir: Path) -> str | None:
    """Return the identity recorded in out_dir/fidelity.json, or None (none there, or unreadable)."""
    try:
        record = read_json(out_dir / FIDELITY_JSON)
    except (OSError, ValueError):  # none yet, or damaged: judge again
        return None
    return record.get("identity") if isinstance(record, dict) else None


def verdict(fidelity: Mapping[str, RowFidelity], changes: Mapping[str, ActionFidelity]) -> str:
    """Return one line: which SAE reconstructs better (lower FVU), with both FVUs and recovered fractions."""
    trained = fidelity["trained"]
    recovered = {name: change.recovered for name, change in changes.items()}
    if "borrowed" not in fidelity:
        actions = f", actions recovered {number(recovered['trained'])}" if recovered else ""
        return f"trained SAE: FVU {number(trained.fvu)}{actions}; no borrowed SAE to compare"
    borrowed = fidelity["borrowed"]
    if trained.fvu is None or borrowed.fvu is None:
        head = "no FVU: the held-out rows do not vary"
    elif trained.fvu == borrowed.fvu:
        head = f"trained and borrowed reconstruct equally well: FVU {number(trained.fvu)}"
    else:
        better = "trained" if trained.fvu < borrowed.fvu else "borrowed"
        head = f"{better} reconstructs better: FVU {number(trained.fvu)} trained vs {number(borrowed.fvu)} borrowed"
    if recovered:
        head += (f"; actions recovered {number(recovered['trained'])} trained vs "
                 f"{number(recovered['borrowed'])} borrowed")
    return head


def fidelity_markdown(record: dict[str, Any]) -> str:
    """Return fidelity.md: the verdict, one table (TABLE_HEADER) and the plot."""
    lines = [f"# SAE fidelity, layer {record['layer']}", "", f"**{record['verdict']}**", "",
             "| " + " | ".join(TABLE_HEADER) + " |", "|" + "---|" * len(TABLE_HEADER)]
    lines += ["| " + " | ".join(row) + " |" for row in table_rows(record)]
    frames = len(record["actions"]["frames"]) if record["actions"] else 0
    lines += [
        "",
        "FVU: fraction of the held-out rows' variance the reconstruction leaves unexplained. L0: non-zero latents "
        f"per row. dead: latents that never fire on these rows; dense: latents firing on more than "
        f"{record['dense_fraction']:.0%} of them.",
        (f"Δ_recon / Δ_zero: mean ‖Δ robot actions‖ over the horizon (action std units, {frames} held-out frames, "
         "the same noise per frame) with the layer's instruction-token residuals replaced by the reconstruction / "
         "zeroed; recovered = 1 − Δ_recon / Δ_zero." if frames else
         "Action change not measured (no policy given)."),
        "",
        f"![fidelity, layer {record['layer']}]({FIDELITY_PNG})",
        "",
    ]
    return "\n".join(lines)


def plot_fidelity(path: Path, record: dict[str, Any]) -> None:
    """FVU per SAE; Δ_recon and Δ_zero per SAE; the live latents' firing frequencies (dead ones counted)."""
    labels = list(record["saes"])
    entries = [record["saes"][label] for label in labels]
    fig = figure((11.0, 3.4))
    ax = fig.add_subplot(1, 3, 1)
    ax.bar(labels, [e["rows"]["fvu"] or 0.0 for e in entries], color=["C0", "C1"][: len(labels)])
    ax.axhline(1.0, color="k", linewidth=0.6, linestyle=":")
    ax.set(ylabel="FVU (held-out rows)", title="reconstruction (lower is better)")
    ax = fig.add_subplot(1, 3, 2)
    if record["actions"]:
        positions = range(len(labels))
        ax.bar([p - 0.2 for p in positions], [e["actions"]["delta_recon"] for e in entries], width=0.4,
               label="reconstruction spliced")
        ax.bar([p + 0.2 for p in positions], [e["actions"]["delta_zero"] for e in entries], width=0.4,
               color="0.6", label="zeroed")
        ax.set_xticks(list(positions), [f"{label}\nrecovered {number(e['actions']['recovered'], '.2f')}"
                                        for label, e in zip(labels, entries, strict=True)])
        ax.legend(fontsize=7)
    else:
        ax.text(0.5, 0.5, "no policy: action change not measured", ha="center", va="center", transform=ax.transAxes)
    ax.set(ylabel="mean ‖Δ actions‖ (std units)", title="action change at the instruction tokens")
    ax = fig.add_subplot(1, 3, 3)
    edges = record["histogram_log10_edges"]
    for label, entry in zip(labels, entries, strict=True):
        ax.stairs(entry["rows"]["firing_histogram"], edges,
                  label=f"{label}: {entry['rows']['dead']} dead, {entry['rows']['dense']} dense")
    ax.axvline(math.log10(record["dense_fraction"]), color="k", linewidth=0.6, linestyle=":",
               label=f"dense: > {record['dense_fraction']:.0%} of rows")
    ax.set(xlabel="log10 firing frequency", ylabel="live latents", title="latent firing")
    ax.legend(fontsize=7)
    for axis in fig.axes:
        axis.title.set_fontsize(9)
    fig.suptitle(f"SAE fidelity, layer {record['layer']}", fontsize=10)
    save_png(fig, path)
