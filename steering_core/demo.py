"""The `latent-steering demo` inputs and summary: a whole run on generated data, offline, in minutes.

`build_demo` writes, under one folder, LIBERO demo files for two concept pairs (open/close the top
drawer of the cabinet, turn on/off the stove), a tiny random pi0.5 checkpoint, a tiny SentencePiece
tokenizer, one tiny SAE per layer, and the run config (`run.yaml`) that ties them together; the
CLI then runs the Prefect flow on it. `summarise` reads the per-layer reports back into a table.
Sizes are tiny on purpose; the real defaults stay in each step's settings.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path
from typing import Any

from steering_core.config import (
    CONFIG_FILE,
    CaptureSection,
    DatasetSection,
    EvaluateSection,
    ModelSection,
    PairSection,
    RunConfig,
    SaeSection,
    SourcesSection,
    SteeringSection,
    write_run_config,
)
from steering_core.fileio import read_json, write_json
from steering_core.layout import SUMMARY_JSON, SUMMARY_MD, layer_dir
from steering_core.synthetic.libero import (
    DRAWER_CLOSE,
    DRAWER_OPEN,
    STOVE_OFF,
    STOVE_ON,
    SyntheticSettings,
    write_demo_suite,
)
from steering_core.synthetic.pi05 import tiny_arch, write_pi05_checkpoint
from steering_core.synthetic.sae import write_sae_folder
from steering_core.synthetic.tokenizer import write_tokenizer

logger = logging.getLogger(__name__)

INPUTS_DIR = "inputs"          # generated inputs, beside the outputs (`data/`) and the run config
ARCH_FILE = "pi05_tiny_arch.json"  # the tiny checkpoint's Pi05Arch
DEMO_LAYERS = (1, 2)           # two of the tiny model's four decoder layers
DEMO_SAE_LATENTS = 256         # d_sae of the tiny SAEs (4x the tiny model's width of 64)
DEMO_IMAGE_SIZE = 64           # dataset frames (real: 256); the tiny model resizes them to 28
DEMO_STEPS = 24                # steps per generated demo (real demos: 100-300)
# The tiny model is random: its dose-responses exercise the whole phase but measure nothing.
TINY_MODEL_NOTE = "Tiny random demo model: these numbers mean nothing; on a real checkpoint they are the result."
DEMO_PAIRS = (
    ("open_vs_close", DRAWER_OPEN, DRAWER_CLOSE),
    ("on_vs_off", STOVE_ON, STOVE_OFF),
)


def build_demo(folder: str | os.PathLike, *, demos_per_task: int = 3, layers: tuple[int, ...] = DEMO_LAYERS) -> Path:
    """Write the demo inputs (those not already there) and the run config under `folder`; return the config path."""
    folder = Path(folder).resolve()
    inputs = folder / INPUTS_DIR
    demos = inputs / "demos"
    if not demos.is_dir():
        logger.info("writing %d demos per task for 4 tasks into %s", demos_per_task, demos)
        write_demo_suite(demos, demos_per_task=demos_per_task,
                         settings=SyntheticSettings(image_size=32, num_steps=DEMO_STEPS, length_jitter=4))
    arch = tiny_arch()
    checkpoint = inputs / "pi05_tiny"
    if not checkpoint.is_dir():
        write_pi05_checkpoint(checkpoint, arch)
    arch_file = inputs / ARCH_FILE
    if not arch_file.is_file():  # for `latent-steering capture --arch-file` in the README walk-through
        write_json(arch_file, arch.model_dump(mode="json"))
    tokenizer = inputs / "tokenizer.model"
    if not tokenizer.is_file():
        write_tokenizer(tokenizer)
    saes = {}
    for layer in layers:
        saes[layer] = inputs / f"sae_{layer_dir(layer)}"
        if not saes[layer].is_dir():
            write_sae_folder(saes[layer], d_in=arch.width, d_sae=DEMO_SAE_LATENTS, hook_layer=layer, seed=layer)
    config = RunConfig(
        name="demo",
        output_root=folder / "data",
        sources=SourcesSection(folders=(demos,)),
        dataset=DatasetSection(repo_id="libero_demo_lerobot", image_size=DEMO_IMAGE_SIZE),
        pairs=tuple(PairSection(name=name, positive=pos, negative=neg) for name, pos, neg in DEMO_PAIRS),
        layers=layers,
        model=ModelSection(checkpoint=checkpoint, tokenizer=tokenizer, arch=arch),
        capture=CaptureSection(batch_size=16, device="cpu", num_workers=0),  # tiny frames: decoding in-process is faster
        sae={layer: SaeSection(path=path) for layer, path in saes.items()},
        steering=SteeringSection(device="cpu", batch_size=256, top_k=5),
        evaluate=EvaluateSection(max_frames=4, noise_seeds=2, bootstrap=200, batch_size=2, device="cpu",
                                 note=TINY_MODEL_NOTE),
    )
    return write_run_config(config, folder / CONFIG_FILE)


def summarise(config: RunConfig) -> list[dict[str, Any]]:
    """Return one row per (layer, pair) from the layer reports: rows, norms and the cosine to the other pairs."""
    rows = []
    for layer in config.layers:
        summary = read_json(config.layer_path(layer) / SUMMARY_JSON)
        for pair in summary["pairs"]:
            others = {key: entry for key, entry in summary["pairwise"].items() if pair["pair"] in key.split("__")}
            rows.append({
                "layer": layer,
                "pair": pair["pair"],
                "positive_rows": pair["counts"]["positive"],
                "negative_rows": pair["counts"]["negative"],
                "latent_norm": pair["latent_norm"],
                "residual_norm": pair["residual_norm"],
                "residual_cosine": {key: entry["residual_cosine"] for key, entry in others.items()},
                "latent_cosine": {key: entry.get("latent_cosine") for key, entry in others.items()},
            })
    return rows


def format_summary(rows: list[dict[str, Any]]) -> str:
    """Return the summary rows as an aligned text table (cosines: with every other pair of the layer)."""
    header = ("layer", "pair", "rows +/-", "latent norm", "residual norm", "cos residual", "cos latent")
    table = [header]
    for row in rows:
        table.append((
            layer_dir(row["layer"]),
            row["pair"],
            f"{row['positive_rows']}/{row['negative_rows']}",
            _number(row["latent_norm"]),
            _number(row["residual_norm"]),
            ", ".join(_number(v) for v in row["residual_cosine"].values()) or "-",
            ", ".join(_number(v) for v in row["latent_cosine"].values()) or "-",
        ))
    widths = [max(len(line[i]) for line in table) for i in range(len(header))]
    return "\n".join("  ".join(cell.ljust(width) for cell, width in zip(line, widths, strict=True)).rstrip()
                     for line in table)


def report_paths(config: RunConfig) -> list[Path]:
    """Return the summary.md of every layer: the steering vectors', then the evaluation's (when it runs)."""
    reports = [config.layer_path(layer) / SUMMARY_MD for layer in config.layers]
    if config.evaluate is not None:
        reports += [config.eval_layer_path(layer) / SUMMARY_MD for layer in config.layers]
    return reports


def _number(value: float | None) -> str:
    return "-" if value is None else f"{value:.3f}"
