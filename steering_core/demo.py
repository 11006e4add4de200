"""The `latent-steering demo` inputs and summary: a whole run on generated data, offline, in minutes.

`build_demo` writes, under one folder, LIBERO demo files for two concept pairs (open/close the top
drawer of the cabinet, turn on/off the stove), a tiny random pi0.5 checkpoint, a tiny SentencePiece
tokenizer, one tiny SAE per layer, and the run config (`run.yaml`) that ties them together; the
CLI then runs the Prefect flow on it. `summarise` reads the per-layer reports back into tables.
`build_planted` writes a second, one-pair run whose concept truly exists in its model
(`steering_core.synthetic.planted`): the evaluation must find it. Sizes are tiny on purpose; the real
defaults stay in each step's settings.
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
    RolloutSection,
    RunConfig,
    SaeSection,
    SaeTrainSection,
    SourcesSection,
    SteeringSection,
    claim_config_file,
    write_run_config,
)
from steering_core.evaluate.plots import layer_label, named
from steering_core.evaluate.report import alpha_text, cross_fitted_choice, fmt, with_ci
from steering_core.layout import DOSE_RESPONSE_FILE, PATHWAYS_FILE, SUMMARY_JSON, SUMMARY_MD, layer_dir
from steering_core.reporting.tables import text_table
from steering_core.rollout.settings import LiberoTask, RolloutPair
from steering_core.sae.fidelity_table import FIDELITY_JSON, TABLE_HEADER, table_rows
from steering_core.storage.fileio import read_json, write_json
from steering_core.synthetic.libero import (
    DRAWER_CLOSE,
    DRAWER_OPEN,
    STOVE_OFF,
    STOVE_ON,
    SyntheticSettings,
    write_demo_suite,
)
from steering_core.synthetic.pi05 import tiny_arch, write_pi05_checkpoint
from steering_core.synthetic.planted import (
    PLANTED_CORPUS,
    PLANTED_LAYER,
    PLANTED_NEGATIVE,
    PLANTED_POSITIVE,
    PLANTED_TASKS,
    plant_concept,
)
from steering_core.synthetic.sae import write_sae_folder
from steering_core.synthetic.tokenizer import LIBERO_INSTRUCTIONS, write_tokenizer
from steering_core.vectors.report import FVU_LIMIT

logger = logging.getLogger(__name__)

INPUTS_DIR = "inputs"          # generated inputs, beside the outputs (`data/`) and the run config
ARCH_FILE = "pi05_tiny_arch.json"  # the tiny checkpoint's Pi05Arch
DEMO_LAYERS = (1, 2)           # two of the tiny model's four decoder layers
DEMO_EXPERT_LAYERS = (2,)      # the action expert's layer whose decision rows are captured and evaluated
DEMO_SAE_LATENTS = 256         # d_sae of the tiny SAEs (4x the tiny model's width of 64)
DEMO_TRAINED_LAYER = 1         # the layer whose SAE the demo trains on its own residuals (judged against the random one)
DEMO_TRAIN = SaeTrainSection(d_sae=DEMO_SAE_LATENTS, k=8, lr=3e-3, batch_size=128, training_rows=96_000,
                             buffer_rows=8192, checkpoints=1, dead_feature_window=200, device="cpu", judge_frames=4)
DEMO_IMAGE_SIZE = 64           # dataset frames (real: 256); the tiny model resizes them to 28
DEMO_STEPS = 24                # steps per generated demo (real demos: 100-300)
DEMO_SYNTHETIC = SyntheticSettings(image_size=32, num_steps=DEMO_STEPS, length_jitter=4)
# Frames the demo's CPU run goes through (every step runs capture and the rollouts' tiny model): 3 demos per task,
# about 330 frames, take 2.5 minutes; the limit, about an hour and a half.
MAX_DEMO_FRAMES = 10_000
# The tiny model is random: its dose-responses exercise the whole phase but measure nothing.
TINY_MODEL_NOTE = "Tiny random demo model: these numbers mean nothing; on a real checkpoint they are the result."
PLANTED_NOTE = ("Planted concept: the two tasks' layer-0 rows differ by exactly one direction, so the right answer "
                "is the mean difference at α = 1 with efficacy 1 on both sides")
DEMO_ROLLOUT_METHODS = ("sae", "mean_difference", "probe")  # head to head in both modes, open and closed loop
PLANTED_DIR = "planted"        # the planted run's folder inside the demo folder
# The closed-loop section: one pair in LIBERO's own scenes (libero_90 task 7 opens the top drawer of KITCHEN_SCENE1,
# task 0 closes the one of KITCHEN_SCENE10), both sides, α toward the other task 0 and 2, 2 episodes of 30 steps.
DEMO_ROLLOUT_PAIR = "open_vs_close"
DEMO_ROLLOUT = RolloutPair(positive=LiberoTask(suite="libero_90", task=7), negative=LiberoTask(suite="libero_90", task=0))
ROLLOUT_NOTE = ("Tiny random demo policy: its success rate (0) says nothing about a real policy; the section shows the "
                "closed loop runs end to end (LIBERO's scenes, openpi's protocol, steering at each α).")
DEMO_PAIRS = (
    ("open_vs_close", DRAWER_OPEN, DRAWER_CLOSE),
    ("on_vs_off", STOVE_ON, STOVE_OFF),
)


def build_demo(folder: str | os.PathLike, *, demos_per_task: int = 3, layers: tuple[int, ...] = DEMO_LAYERS) -> Path:
    """Write the demo inputs (those not already there) and the run config under `folder`; return the config path.

    A `run.yaml` already in `folder` that is not this demo's is refused before anything is written."""
    folder = Path(folder).resolve()
    config = demo_config(folder, layers)
    claim_config_file(folder / CONFIG_FILE, config)
    inputs = folder / INPUTS_DIR
    demos = inputs / "demos"
    if not demos.is_dir():
        logger.info("writing %d demos per task for 4 tasks into %s", demos_per_task, demos)
        write_demo_suite(demos, demos_per_task=demos_per_task, settings=DEMO_SYNTHETIC)
    arch = config.model.arch
    if not config.model.checkpoint.is_dir():
        write_pi05_checkpoint(config.model.checkpoint, arch)
    arch_file = inputs / ARCH_FILE
    if not arch_file.is_file():  # for `latent-steering capture --arch-file` in the README walk-through
        write_json(arch_file, arch.model_dump(mode="json"))
    if not config.model.tokenizer.is_file():
        write_tokenizer(config.model.tokenizer)
    for layer in layers:
        if not (sae := config.sae[layer].path).is_dir():
            write_sae_folder(sae, d_in=arch.width, d_sae=DEMO_SAE_LATENTS, hook_layer=layer, seed=layer)
    return write_run_config(config, folder / CONFIG_FILE)


def demo_config(folder: Path, layers: tuple[int, ...] = DEMO_LAYERS) -> RunConfig:
    """Return the demo's run config for the (absolute) demo folder `folder`."""
    inputs = folder / INPUTS_DIR
    return RunConfig(
        name="demo",
        output_root=folder / "data",
        sources=SourcesSection(folders=(inputs / "demos",)),
        dataset=DatasetSection(repo_id="libero_demo_lerobot", image_size=DEMO_IMAGE_SIZE),
        pairs=tuple(PairSection(name=name, positive=pos, negative=neg) for name, pos, neg in DEMO_PAIRS),
        layers=layers,
        model=ModelSection(checkpoint=inputs / "pi05_tiny", tokenizer=inputs / "tokenizer.model", arch=tiny_arch()),
        capture=CaptureSection(batch_size=16, device="cpu", num_workers=0),  # tiny frames: decoding in-process is faster
        sae={layer: SaeSection(path=inputs / f"sae_{layer_dir(layer)}",
                               train=DEMO_TRAIN if layer == DEMO_TRAINED_LAYER else None) for layer in layers},
        steering=SteeringSection(device="cpu", batch_size=256, top_k=5),
        evaluate=EvaluateSection(max_frames=4, noise_seeds=2, bootstrap=200, batch_size=2, device="cpu",
                                 note=TINY_MODEL_NOTE, expert_layers=DEMO_EXPERT_LAYERS),
        rollout=RolloutSection(pairs={DEMO_ROLLOUT_PAIR: DEMO_ROLLOUT}, layers=layers[:1], alphas=(0.0, 1.0),
                               methods=DEMO_ROLLOUT_METHODS, modes=("add", "clamp"), sides=("negative",),
                               episodes=2, max_steps=30, random_directions=0, wrong_concept=False,
                               instruction_swap=False, device="cpu", note=ROLLOUT_NOTE),
    )


def build_planted(folder: str | os.PathLike, *, demos_per_task: int = 6) -> Path:
    """Write the planted-concept run (inputs not already there, and its run config) under `folder`; return the
    config path. Half the episodes are held out, so selection and report halves hold different episodes.

    A `run.yaml` already in `folder` that is not this run's is refused before anything is written."""
    folder = Path(folder).resolve()
    config = planted_config(folder)
    claim_config_file(folder / CONFIG_FILE, config)
    demos, arch = config.sources.folders[0], config.model.arch
    tokenizer, checkpoint, sae = config.model.tokenizer, config.model.checkpoint, config.sae[PLANTED_LAYER].path
    if not demos.is_dir():
        write_demo_suite(demos, demos_per_task=demos_per_task, tasks=PLANTED_TASKS,
                         settings=SyntheticSettings(image_size=32, num_steps=16, length_jitter=2))
    if not tokenizer.is_file():
        write_tokenizer(tokenizer, [*LIBERO_INSTRUCTIONS, *PLANTED_CORPUS])
    if not checkpoint.is_dir():
        write_pi05_checkpoint(checkpoint, arch)
        plant_concept(checkpoint, tokenizer, arch)
    if not sae.is_dir():
        write_sae_folder(sae, d_in=arch.width, d_sae=2 * arch.width, hook_layer=PLANTED_LAYER, seed=0)
    return write_run_config(config, folder / CONFIG_FILE)


def planted_config(folder: Path) -> RunConfig:
    """Return the planted-concept run's config for the (absolute) folder `folder`."""
    inputs = folder / INPUTS_DIR
    return RunConfig(
        name="planted", output_root=folder / "data", sources=SourcesSection(folders=(inputs / "demos",)),
        dataset=DatasetSection(repo_id="planted_lerobot", image_size=32),
        pairs=(PairSection(name="planted", positive=PLANTED_POSITIVE, negative=PLANTED_NEGATIVE),),
        layers=(PLANTED_LAYER,),
        model=ModelSection(checkpoint=inputs / "pi05_planted", tokenizer=inputs / "tokenizer.model", arch=tiny_arch()),
        capture=CaptureSection(batch_size=16, device="cpu", num_workers=0),
        sae={PLANTED_LAYER: SaeSection(path=inputs / "sae")},
        steering=SteeringSection(device="cpu", batch_size=256, top_k=5),
        evaluate=EvaluateSection(holdout_fraction=0.5, max_frames=12, noise_seeds=2, bootstrap=200, batch_size=6,
                                 device="cpu", note=PLANTED_NOTE),
    )


def check_demo_request(folder: str | os.PathLike, demos_per_task: int) -> None:
    """Raise before anything is written when `folder` (or its planted run's folder) holds a run.yaml not the demo's,
    or when `demos_per_task` makes more frames than `MAX_DEMO_FRAMES` (estimated from the demo's settings)."""
    tasks = len(DEMO_PAIRS) * 2
    frames = demos_per_task * tasks * (DEMO_SYNTHETIC.num_steps + DEMO_SYNTHETIC.length_jitter)
    if frames > MAX_DEMO_FRAMES:
        raise ValueError(f"demo --demos-per-task {demos_per_task:,}: an estimated {frames:,} frames = {tasks} tasks x "
                         f"{demos_per_task:,} demos x up to {DEMO_SYNTHETIC.num_steps + DEMO_SYNTHETIC.length_jitter} "
                         f"steps, each run through the pipeline on the CPU; expected at most {MAX_DEMO_FRAMES:,} (about "
                         "an hour and a half): lower --demos-per-task, or make larger inputs with make-demos and "
                         "`run --config` them")
    folder = Path(folder).resolve()
    claim_config_file(folder / CONFIG_FILE, demo_config(folder))
    claim_config_file(folder / PLANTED_DIR / CONFIG_FILE, planted_config(folder / PLANTED_DIR))


def summarise(config: RunConfig) -> dict[str, list[dict[str, Any]]]:
    """Return the layer reports as rows: `pairs`, one per (layer, pair); `between`, one per two pairs of a layer."""
    pairs, between = [], []
    for layer in config.layers:
        summary = read_json(config.layer_path(layer) / SUMMARY_JSON)
        for pair in summary["pairs"]:
            fidelity = pair["fidelity"]
            pairs.append({
                "layer": layer,
                "pair": pair["pair"],
                "positive_rows": pair["counts"]["positive"],
                "negative_rows": pair["counts"]["negative"],
                "latent_norm": pair["latent_norm"],
                "residual_norm": pair["residual_norm"],
                "decoded_cosine": pair["decoded_vs_mean_difference_cosine"],
                "fvu": (fidelity["positive"]["fvu"], fidelity["negative"]["fvu"]),
            })
        for key, entry in summary["pairwise"].items():
            between.append({
                "layer": layer,
                "pairs": tuple(key.split("__")),
                "residual_cosine": entry["residual_cosine"],
                "latent_cosine": entry.get("latent_cosine"),
                "mean_difference_cosine": entry.get("mean_difference_cosine"),
            })
    trained = [read_json(config.sae_layer_path(layer) / FIDELITY_JSON) for layer in config.trained_layers]
    return {"pairs": pairs, "between": between, "evaluation": evaluation_answer(config), "trained_saes": trained}


def format_trained(records: list[dict[str, Any]]) -> str:
    """Return the judgement of each SAE trained on the run's residuals: its verdict and table."""
    lines = []
    for record in records:
        lines += [f"SAE trained on this run's residuals, layer {record['layer']}, against the borrowed one "
                  "(held-out episodes): " + record["verdict"], text_table(TABLE_HEADER, table_rows(record))]
    return "\n".join(lines)


def evaluation_answer(config: RunConfig) -> list[dict[str, Any]]:
    """Return one row per pair: the (layer, direction, α) chosen on half 0 of the held-out episodes over every
    evaluated layer of both pathways, its summary row (α in both units, per-side efficacy, p) and the
    cross-fitted efficacy of that choice (read on the other half, both ways)."""
    rows = []
    for pair in config.pairs:
        candidates, summary_rows = [], {}
        for layer, stream in config.eval_layers():
            record = read_json(config.eval_layer_path(layer, stream) / pair.name / f"{DOSE_RESPONSE_FILE}.json")
            for name in named(record):
                entry = record["directions"][name]
                key = (layer_label(layer, stream), name)
                candidates.append({"layer": key[0], "direction": name, "alphas": record["alphas"],
                                   "efficacy_half": entry["efficacy_half"],
                                   "alphas_vector_units": entry["alphas_vector_units"]})
                summary_rows[key] = entry["best"] | {"note": record.get("note")}
        choice = cross_fitted_choice(candidates)
        if choice is not None:
            first = choice["chosen"][0]
            rows.append({"pair": pair.name, "layer": first["layer"], "direction": first["direction"],
                         "cross_fitted": choice["efficacy"], **summary_rows[(first["layer"], first["direction"])]})
    return rows


def format_evaluation(rows: list[dict[str, Any]]) -> str:
    """Return the evaluation's answer: a table, one row per pair, and the sentence that says what it means."""
    table = text_table(
        ("pair", "best direction", "α (R / vector)", "efficacy: negative-task frames", "positive-task frames", "p"),
        [(row["pair"], f"{row['direction']}, {row['layer']}", alpha_text(row),
          with_ci(row["efficacy_negative"], row["efficacy_negative_ci"]),
          with_ci(row["efficacy_positive"], row["efficacy_positive_ci"]), fmt(row.get("p_random"))) for row in rows])
    lines = ["Steering evaluation, per pair (the best layer and direction chosen on one half of the held-out "
             "episodes; efficacy 1 = steering reproduces the instruction swap, 0 = no effect, in action std units):",
             table, ""]
    for row in rows:
        verdict = ("better than" if row.get("p_random") is not None and row["p_random"] < 0.05
                   else "not distinguishable from")
        lines.append(f"{row['pair']}: {row['direction']} at {row['layer']} moves the actions "
                     f"{fmt(row['efficacy'])} of the way to the other task's instruction (cross-fitted), "
                     f"{verdict} random directions of the residual stream (p = {fmt(row.get('p_random'))}).")
    if any(row.get("note") == TINY_MODEL_NOTE for row in rows):
        lines.append("The demo's policy is tiny and random: these numbers exercise the evaluation and mean nothing "
                     "about a real policy.")
    return "\n".join(lines)


def format_summary(summary: dict[str, list[dict[str, Any]]], *, random_sae: bool) -> str:
    """Return the summary as text: a table per pair, a table between pairs, and what the FVU says.

    `random_sae`: the SAEs are the demo's random ones, so FVU > 1 is expected and explained rather
    than flagged.
    """
    poor = set()
    per_pair = []
    for row in summary["pairs"]:
        bad = any(fvu is not None and fvu > FVU_LIMIT for fvu in row["fvu"])
        if bad and not random_sae:
            poor.add(f"{row['pair']} ({layer_dir(row['layer'])})")
        per_pair.append((
            layer_dir(row["layer"]),
            row["pair"],
            f"{row['positive_rows']}/{row['negative_rows']}",
            _number(row["latent_norm"]),
            _number(row["residual_norm"]),
            _number(row["decoded_cosine"]),
            " / ".join(_number(v) for v in row["fvu"]) + (" !" if bad and not random_sae else ""),
        ))
    lines = ["Steering vectors, per pair:",
             text_table(("layer", "pair", "rows +/-", "latent norm", "residual norm", "cos(decoded, mean diff)",
                         "FVU +/-"), per_pair)]
    if summary["between"]:
        lines += ["", "Between pairs (cosine of the two pairs' directions):",
                  text_table(("layer", "pairs", "residual", "latent", "mean diff"), [
                      (layer_dir(row["layer"]), " vs ".join(row["pairs"]), _number(row["residual_cosine"]),
                       _number(row["latent_cosine"]), _number(row["mean_difference_cosine"]))
                      for row in summary["between"]])]
    lines.append("")
    if random_sae:
        lines.append("The demo's borrowed SAEs are random (untrained, tiny), so they do not reconstruct the residuals: an "
                     "FVU (fraction of variance unexplained) of 4-7 is expected there and nothing is broken"
                     + ("; the layers listed below steer through an SAE trained on the demo's own residuals instead"
                        if summary.get("trained_saes") else "")
                     + ". On a real SAE an FVU above 1 is flagged.")
    elif poor:
        lines.append(f"! FVU > {FVU_LIMIT:g} for {', '.join(sorted(poor))}: the SAE does not reconstruct these "
                     "residuals, so its latent directions say little about them (the residual-space "
                     "mean difference still holds).")
    else:
        lines.append(f"FVU (fraction of variance unexplained by the SAE) is at most {FVU_LIMIT:g} everywhere.")
    if summary.get("trained_saes"):
        lines += ["", format_trained(summary["trained_saes"])]
    if summary.get("evaluation"):
        lines += ["", format_evaluation(summary["evaluation"])]
    return "\n".join(lines)


def report_paths(config: RunConfig) -> list[Path]:
    """Return the summary.md of every layer: the steering vectors', then the evaluation's (when it runs), the
    pathways table (with expert layers), then the rollouts' (with a rollout section)."""
    reports = [config.layer_path(layer) / SUMMARY_MD for layer in config.layers]
    reports += [config.eval_layer_path(layer, stream) / SUMMARY_MD for layer, stream in config.eval_layers()]
    if config.expert_layers:
        reports.append(config.eval_root / f"{PATHWAYS_FILE}.md")
    reports += [config.rollout_layer_path(layer) / SUMMARY_MD for layer in config.rollout_layers]
    return reports


def format_rollouts(config: RunConfig) -> str:
    """Return the closed-loop answer of every rolled-out (pair, layer, side, steered direction), after the rollouts'
    note."""
    lines = []
    for layer in config.rollout_layers:
        summary = read_json(config.rollout_layer_path(layer) / SUMMARY_JSON)
        lines += [f"Closed-loop rollouts in LIBERO, {layer_dir(layer)} (success toward the other task, Wilson 95%; "
                  "paired exact McNemar tests, best α cross-fitted):"]
        lines += [summary["note"]] if summary.get("note") else []
        lines += [f"  {pair['pair']}, {row['side']} side, {row['condition']}: {row['text']}" for pair in summary["pairs"]
                  for row in pair["answers"]]
    return "\n".join(lines)


def _number(value: float | None) -> str:
    return "-" if value is None else f"{value:.3f}"
