"""Path templates of the on-disk layout (the seed's, kept). Build paths only through these."""

from __future__ import annotations

import re

LAYER_DIR = "layer{layer:02d}"                      # data/residuals/<pair>_slices/layer12/
FILTERED_DIR = "libero_filtered/{suite}"            # selected .hdf5 links + selection.json
SELECTION_FILE = "selection.json"
LEROBOT_DIR = "libero_lerobot/{repo_id}"
MANIFEST_FILE = "manifests/{pair}.json"
CONCEPT_MAP_FILE = "manifests/{pair}_concept_map.json"
RESIDUALS_RUN_DIR = "residuals/{run}"
DECISION_RUN_DIR = "residuals/{run}_decision"       # the action expert's `decision` rows (evaluate.expert_layers)
SLICES_DIR = "residuals/{pair}_slices"
DECISION_SLICES_DIR = "residuals/{pair}_decision_slices"  # layerKK/<concept>.pt: expert layer KK
EXPERT_LAYER_DIR = "expert_layer{layer:02d}"        # steering_eval/expert_layerKK/<pair>/: action-expert layer KK
SLICE_INDEX_FILE = "index.json"                     # beside the slices of one layer: settings, concepts
SPLIT_FILE = "manifests/{pair}_split.json"   # held-out episodes per task (phase 4 evaluates on them)
STEERING_ROOT = "latent_steering"
SAES_DIR = "saes/{run}"                    # layerNN/: an SAE trained on the run's residuals, its judgement, features
TRAINED_SAE_DIR = "sae"                    # in saes/<run>/layerNN/: the SAE in SAELens's format (+ training.json)
FEATURE_PAGE_FILE = "features.html"        # in saes/<run>/layerNN/: the trained SAE's static feature page
NEURONPEDIA_DIR = "neuronpedia"            # in saes/<run>/layerNN/: its features in Neuronpedia's export layout
STEERING_EVAL_ROOT = "steering_eval"       # phase 4: steering_eval/layerNN/<pair>/ and per-layer summaries
PATHWAYS_FILE = "pathways"                 # + .md / .json in STEERING_EVAL_ROOT: language model vs action expert
# Files of one steering layer folder (STEERING_ROOT/layerNN/) and of its pair folders (layerNN/<pair>/).
PAIR_SUMMARY_FILE = "directions.json"
PAIRWISE_STATS_FILE = "pairwise_stats"  # + .pt / .json
SUMMARY_MD = "summary.md"
SUMMARY_JSON = "summary.json"
# Files of one evaluation pair folder (STEERING_EVAL_ROOT/layerNN/<pair>/).
DOSE_RESPONSE_FILE = "dose_response"  # + .json / .safetensors
EFFICACY_PLOT = "efficacy_vs_alpha.png"
SHIFT_PLOT = "shift_vs_alpha.png"
TRAJECTORY_PLOT = "trajectory.png"
# phase 5: ROLLOUTS_ROOT/layerNN/<pair>/<cell>/ per cell; the pair's table and PNGs in <pair>/, summaries in layerNN/
ROLLOUTS_ROOT = "rollouts"
ROLLOUT_FILE = "rollouts"  # + .json / .safetensors in a cell folder
ROLLOUT_VIDEO = "{cell}_ep{episode}_{outcome}.mp4"  # in a cell folder: e.g. negative_sae_a+2_ep0_toward.mp4
ROLLOUT_PAIR_TABLE = "cells"  # + .md / .json in a pair folder: one row per cell
SUCCESS_PLOT = "success_vs_alpha.png"
JOINTS_PLOT = "joint_trajectories.png"
_UNSAFE = re.compile(r"[^A-Za-z0-9_.+-]")


MAX_NAME_BYTES = 200  # a name part, before the suffixes a step adds (.json, .tmp-<id>, .published.json)


def check_name(name: str, what: str, *, nested: bool = False) -> str:
    """Return `name` when it can name a file or folder under an output root; ValueError naming `what` otherwise.

    Refused: empty, `.` or `..`, a `/` (unless `nested`: then `/`-separated parts, each checked, as in the
    repo id `org/name`), a backslash, a NUL or a leading `~`: anything that could land outside the root.
    """
    parts = name.split("/") if nested else [name]
    bad = [part for part in parts if part in ("", ".", "..") or any(c in part for c in "/\\\0") or part[:1] == "~"]
    long = [part for part in parts if len(part.encode("utf-8", "surrogatepass")) > MAX_NAME_BYTES]
    if long:
        raise ValueError(f"{what} {name[:60]!r}...: a part of {len(long[0].encode('utf-8', 'surrogatepass'))} bytes; "
                         f"expected at most {MAX_NAME_BYTES} (a file system takes 255, suffixes are added)")
    if bad or not name.strip():
        shape = "`/`-separated names" if nested else "one file or folder name"
        raise ValueError(f"{what} {name!r} is not a name a path can be built from: expected {shape} without "
                         "`..`, `.`, empty parts, backslashes or a leading `~` (it must stay under its root)")
    return name


def layer_dir(layer: int) -> str:
    """Return the folder name of one layer, e.g. `layer12`."""
    return LAYER_DIR.format(layer=layer)


def stream_layer_dir(layer: int, stream: str) -> str:
    """Return the folder name of one layer of a stream: `layer12` (language model) or `expert_layer03`."""
    return EXPERT_LAYER_DIR.format(layer=layer) if stream == "expert" else layer_dir(layer)


def rollout_cell_dir(side: str, condition: str, alpha: float) -> str:
    """Return the folder name of one rollout cell, e.g. `negative_sae_a+2`, `positive_probe+clamp_a-0.5`,
    `positive_wrong_concept-on_vs_off-sae_a-1.5` (characters other than letters, digits and `_.+-` become `-`;
    α = -0 is written `+0`)."""
    return _UNSAFE.sub("-", f"{side}_{condition}_a{alpha + 0.0:+g}")


def rollout_video_file(cell: str, episode: int, outcome: str) -> str:
    """Return the MP4 file name of one episode of a cell, e.g. `negative_sae_a+2_ep0_toward.mp4`."""
    return ROLLOUT_VIDEO.format(cell=cell, episode=episode, outcome=outcome)
