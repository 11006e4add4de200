"""Per-layer report of the steering outputs: summary.md, summary.json and PNG plots.

Reads only what the steering steps wrote (pairwise_stats.json, each pair's directions.json and
the safetensors files they name), so it can run on its own over an existing output folder.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path
from typing import Any

import numpy as np
import torch
from safetensors.torch import load_file

from steering_core.layout import FEATURE_PAGE_FILE, PAIR_SUMMARY_FILE, PAIRWISE_STATS_FILE, SUMMARY_JSON, SUMMARY_MD
from steering_core.reporting.plots import figure, save_png
from steering_core.sae.fidelity_table import FIDELITY_JSON, FIDELITY_MD, FIDELITY_PNG, TABLE_HEADER, table_rows
from steering_core.sae.registry import NEURONPEDIA_FEATURE_URL
from steering_core.storage.fileio import read_json, write_json, write_text

logger = logging.getLogger(__name__)

REPORT_FORMAT_VERSION = 1
COSINE_PLOT = "pairwise_cosine.png"
TOP_LATENTS_PLOT = "top_latents_{pair}.png"
FVU_LIMIT = 1.0  # above it the SAE explains less of the residuals' variance than their mean does


def write_report(layer_path: Path, *, top_k: int = 20, trained_sae: Path | None = None) -> Path:
    """Write summary.md, summary.json and plots for one layer folder; return the summary.md path.

    `trained_sae`: the folder of the layer's SAE trained on the run's residuals (`saes/<run>/layerNN`), whose
    judgement against the borrowed SAE and feature page the report shows.
    """
    pairwise = read_json(layer_path / f"{PAIRWISE_STATS_FILE}.json")
    pairs = [_pair_summary(layer_path / name, top_k) for name in pairwise["pairs"]]
    sae = next((pair["sae"] for pair in pairs if pair["sae"] is not None), None)
    plots = {}
    if len(pairs) > 1:
        plots["pairwise_cosine"] = _plot_cosines(layer_path / COSINE_PLOT, pairwise)
    for pair in pairs:
        if pair["top_latents"]:
            plots[f"top_latents/{pair['pair']}"] = _plot_top_latents(
                layer_path / TOP_LATENTS_PLOT.format(pair=pair["pair"]), pair
            )
    summary = {
        "format_version": REPORT_FORMAT_VERSION,
        "layer": layer_path.name,
        "sae_used": pairwise["sae_used"],
        "sae": sae,
        "pairs": pairs,
        "pairwise": pairwise["entries"],
        "plots": plots,
        "trained_sae": _trained_sae(layer_path, trained_sae) if trained_sae is not None else None,
    }
    write_json(layer_path / SUMMARY_JSON, summary)
    md_path = layer_path / SUMMARY_MD
    write_text(md_path, _markdown(summary))
    logger.info("report written to %s", md_path)
    return md_path


def top_latents(
    direction: torch.Tensor,
    firing: dict[str, torch.Tensor],
    means: dict[str, torch.Tensor],
    k: int,
    neuronpedia_id: str | None,
) -> list[dict[str, Any]]:
    """Return the k latents with the largest |direction| value: index, value, firing rates, means and link."""
    order = torch.argsort(direction.abs(), descending=True, stable=True)[:k]
    return [
        {
            "index": int(index),
            "value": float(direction[index]),
            "firing_rate_positive": float(firing["positive"][index]),
            "firing_rate_negative": float(firing["negative"][index]),
            "mean_positive": float(means["positive"][index]),
            "mean_negative": float(means["negative"][index]),
            "neuronpedia": NEURONPEDIA_FEATURE_URL.format(neuronpedia_id=neuronpedia_id, index=int(index))
            if neuronpedia_id
            else None,
        }
        for index in order
    ]


def _trained_sae(layer_path: Path, folder: Path) -> dict[str, Any]:
    """Return the trained SAE's judgement (verdict and table rows) and where its files are, relative to the report."""
    record = read_json(folder / FIDELITY_JSON)
    where = Path(os.path.relpath(folder, layer_path)).as_posix()
    return {"folder": where, "verdict": record["verdict"], "table": [list(row) for row in table_rows(record)],
            "fidelity": f"{where}/{FIDELITY_MD}", "plot": f"{where}/{FIDELITY_PNG}",
            "feature_page": f"{where}/{FEATURE_PAGE_FILE}"}


def _pair_summary(pair_path: Path, top_k: int) -> dict[str, Any]:
    """Return one pair's report entry from its directions.json and tensors."""
    info = read_json(pair_path / PAIR_SUMMARY_FILE)
    entry = {key: info.get(key) for key in (
        "pair", "positive_concept", "negative_concept", "counts", "method", "include_decoder_bias",
        "direction_space", "latent_norm", "residual_norm", "mean_difference_norm",
        "decoded_vs_mean_difference_cosine", "sae",
    )}
    entry["fidelity"] = {side: {"fvu": c["fvu"], "mean_l0": c["mean_l0"]} for side, c in info["concepts"].items()}
    effect = (info.get("methods") or {}).get("sae_effect")  # older outputs list no methods
    entry["sae_effect"] = effect["record"] if effect else None
    entry["top_latents"] = []
    if info["sae"] is None:
        entry["residual_norm"] = info["mean_difference_norm"]
        return entry
    latent_file = pair_path / info["files"]["latent_direction"]["safetensors"]
    direction = load_file(latent_file)["latent_direction"]
    firing, means = {}, {}
    for side, concept in info["concepts"].items():
        stats_json = (pair_path / concept["stats"]).resolve()
        tensors = load_file(stats_json.with_name(read_json(stats_json)["tensors"]))
        firing[side], means[side] = tensors["firing_rate"], tensors["latent_mean"]
    entry["top_latents"] = top_latents(direction, firing, means, top_k, info["sae"].get("neuronpedia_id"))
    return entry


def _cosine_matrix(pairwise: dict[str, Any], key: str) -> np.ndarray:
    """Return the symmetric (pairs, pairs) matrix of one cosine entry, ones on the diagonal."""
    names = pairwise["pairs"]
    matrix = np.eye(len(names))
    for i, a in enumerate(names):
        for j in range(i + 1, len(names)):
            matrix[i, j] = matrix[j, i] = pairwise["entries"][f"{a}__{names[j]}"][key]
    return matrix


def _plot_cosines(path: Path, pairwise: dict[str, Any]) -> str:
    """Draw the pairwise cosine heatmaps (residual, and latent when an SAE was used); return the file name."""
    keys = ["residual_cosine"] + (["latent_cosine"] if pairwise["sae_used"] else [])
    names = pairwise["pairs"]
    side = 1.2 + 0.75 * len(names)
    fig = figure(figsize=(side * len(keys) + 2.5, side + 1.2))
    axes = fig.subplots(1, len(keys), squeeze=False)
    for column, (ax, key) in enumerate(zip(axes[0], keys, strict=True)):
        matrix = _cosine_matrix(pairwise, key)
        image = ax.imshow(matrix, vmin=-1, vmax=1, cmap="RdBu_r")
        ax.set_xticks(range(len(names)), names, rotation=40, ha="right")
        ax.set_yticks(range(len(names)), names if column == 0 else [])  # rows are the same pairs in every panel
        ax.set_title(key.replace("_", " "))
        for (i, j), value in np.ndenumerate(matrix):
            ax.text(j, i, f"{value:.2f}", ha="center", va="center", color="white" if abs(value) > 0.6 else "black")
    fig.colorbar(image, ax=axes[0].tolist(), shrink=0.8, label="cosine of the two pairs' directions")
    save_png(fig, path)
    return path.name


def _plot_top_latents(path: Path, pair: dict[str, Any]) -> str:
    """Draw one pair's top latents as horizontal bars (value of the latent direction); return the file name."""
    latents = pair["top_latents"]
    labels = [
        f"#{item['index']}  ({item['firing_rate_positive']:.0%} | {item['firing_rate_negative']:.0%})"
        for item in latents
    ]
    values = [item["value"] for item in latents]
    fig = figure(figsize=(8, 1.4 + 0.32 * len(latents)))
    ax = fig.subplots()
    ax.barh(range(len(values)), values, color=["#c0392b" if v > 0 else "#2471a3" for v in values])
    ax.set_yticks(range(len(values)), labels, fontsize=8)
    ax.invert_yaxis()
    ax.axvline(0, color="black", linewidth=0.8)
    ax.set_xlabel("latent direction value (mean positive - mean negative)")
    ax.set_title(
        f"{pair['pair']}: top {len(latents)} latents\n"
        f"red: more active in '{pair['positive_concept']}', blue: in '{pair['negative_concept']}'\n"
        "label: latent index (firing rate on positive | negative rows)",
        fontsize=9,
    )
    save_png(fig, path)
    return path.name


def _number(value: float | None, spec: str = ".3f") -> str:
    """Return a formatted number, or an en dash for a missing one."""
    return "–" if value is None else format(value, spec)


def _markdown(summary: dict[str, Any]) -> str:
    """Return the summary.md text."""
    sae = summary["sae"]
    lines = [f"# Steering vectors, {summary['layer']}", ""]
    if sae is None:
        lines += ["**No SAE was used**: every direction is the residual-space difference of concept means.", ""]
    else:
        name = f"{sae['release']} / {sae['sae_id']}" if sae.get("release") else sae["source"]
        lines += [
            f"SAE: `{name}` ({sae['architecture']}, d_in {sae['d_in']}, d_sae {sae['d_sae']}, "
            f"normalisation {sae['normalize_activations']}, hook `{sae['hook_name']}`"
            + (f", Neuronpedia `{sae['neuronpedia_id']}`" if sae.get("neuronpedia_id") else "") + ").",
            "",
            "`residual_direction` = latent direction @ W_dec"
            + (" + b_dec (seed-compatible option)" if summary["pairs"][0]["include_decoder_bias"] else " (no b_dec)")
            + (". The SAE was trained on this run's own pi0.5 residuals (below: how it compares with the borrowed one)"
               if summary["trained_sae"] else ". The SAE was trained on Gemma text, not on pi0.5's fine-tuned LM")
            + ": check the fidelity below (FVU = fraction of variance unexplained by the reconstruction; "
            "L0 = active latents per row).",
            "",
        ]
        if summary["pairs"][0]["direction_space"] != "residual":
            lines += [f"Directions live in the SAE's {summary['pairs'][0]['direction_space']}.", ""]
    # narrow tables rather than one wide one: the Prefect UI clips wide tables
    lines += ["## Pairs", "", "| pair | positive (rows) | negative (rows) |", "|---|---|---|"]
    lines += [f"| {pair['pair']} | {pair['positive_concept']} ({pair['counts']['positive']}) | "
              f"{pair['negative_concept']} ({pair['counts']['negative']}) |" for pair in summary["pairs"]]
    lines += [
        "",
        "## Directions",
        "",
        "| pair | residual norm | latent norm | mean-diff norm | cos(decoded, mean diff) |",
        "|---|---|---|---|---|",
    ]
    lines += [f"| {pair['pair']} | {_number(pair['residual_norm'])} | {_number(pair['latent_norm'])} | "
              f"{_number(pair['mean_difference_norm'])} | {_number(pair['decoded_vs_mean_difference_cosine'])} |"
              for pair in summary["pairs"]]
    if sae is not None:
        lines += ["", "## SAE fidelity on the concept rows", "", "| pair | FVU + | FVU - | L0 + | L0 - |",
                  "|---|---|---|---|---|"]
        lines += [f"| {pair['pair']} | {_number(pair['fidelity']['positive']['fvu'])} | "
                  f"{_number(pair['fidelity']['negative']['fvu'])} | {_number(pair['fidelity']['positive']['mean_l0'], '.1f')} | "
                  f"{_number(pair['fidelity']['negative']['mean_l0'], '.1f')} |" for pair in summary["pairs"]]
    poor = [f"{pair['pair']} ({side})" for pair in summary["pairs"] for side, fid in pair["fidelity"].items()
            if fid["fvu"] is not None and fid["fvu"] > FVU_LIMIT]
    if poor and sae is not None:
        lines += ["", f"**FVU > {FVU_LIMIT:g} for {', '.join(poor)}: the SAE does not reconstruct these residuals**, "
                  "so its latent directions say little about them; the residual-space mean difference still holds."]
    if trained := summary["trained_sae"]:
        lines += ["", "## The SAE trained on this run's residuals, against the borrowed one (held-out episodes)", "",
                  f"**{trained['verdict']}**", "", "| " + " | ".join(TABLE_HEADER) + " |",
                  "|" + "---|" * len(TABLE_HEADER)]
        lines += ["| " + " | ".join(row) + " |" for row in trained["table"]]
        lines += ["", f"Details: [{trained['fidelity']}]({trained['fidelity']}); its latents, their top frames and "
                  f"tokens: [feature page]({trained['feature_page']}).", "", f"![fidelity]({trained['plot']})"]
    if summary["pairwise"]:
        lines += ["", "## Pairwise cosines", "", "| pairs | residual cosine | latent cosine | mean-diff cosine |",
                  "|---|---|---|---|"]
        for key, entry in summary["pairwise"].items():
            lines.append(f"| {key.replace('__', ' vs ')} | {_number(entry['residual_cosine'])} | "
                         f"{_number(entry.get('latent_cosine'))} | {_number(entry.get('mean_difference_cosine'))} |")
        lines += ["", f"![pairwise cosines]({summary['plots']['pairwise_cosine']})"]
    feature_page = summary["trained_sae"]["feature_page"] if summary["trained_sae"] else None
    for pair in summary["pairs"]:
        if pair["top_latents"]:
            lines += ["", f"## {pair['pair']}: top latents", "",
                      "| latent | value | fires + | fires - | mean + | mean - |", "|---|---|---|---|---|---|"]
            for item in pair["top_latents"]:
                index = f"[{item['index']}]({item['neuronpedia']})" if item["neuronpedia"] else str(item["index"])
                lines.append(
                    f"| {index} | {item['value']:+.4f} | {item['firing_rate_positive']:.1%} | "
                    f"{item['firing_rate_negative']:.1%} | {item['mean_positive']:.4f} | {item['mean_negative']:.4f} |"
                )
            plot = summary["plots"][f"top_latents/{pair['pair']}"]
            lines += ["", f"![top latents of {pair['pair']}]({plot})"]
        if pair["sae_effect"]:
            lines += ["", *_effect_lines(pair["pair"], pair["sae_effect"], feature_page)]
    return "\n".join(lines) + "\n"


def _effect_lines(pair: str, record: dict[str, Any], feature_page: str | None) -> list[str]:
    """Return the markdown of one pair's `sae_effect` latents, each linked to its section of the trained SAE's
    feature page when the layer steers through that SAE."""
    excluded = record["excluded"]
    lines = [f"## {pair}: sae_effect latents", "",
             f"By |Cohen's d|, among latents firing in at least {record['min_episodes']} training episodes "
             f"(excluded: {excluded['memorised']} memorised, {excluded['never_fire']} never fire, "
             f"{excluded['zero_effect']} zero effect, {excluded['zero_variance']} zero variance).", "",
             "| latent | Cohen's d | mean diff | episodes | fires |", "|---|---|---|---|---|"]
    for item in record["latents"]:
        latent = f"[{item['latent']}]({feature_page}#latent-{item['latent']})" if feature_page else str(item["latent"])
        lines.append(f"| {latent} | {item['cohen_d']:+.3f} | {item['mean_difference']:+.4f} | {item['episodes']} | "
                     f"{item['frequency']:.1%} |")
    return lines
