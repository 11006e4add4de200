"""Steering vectors: concept residuals -> streaming SAE latent statistics -> per-pair directions.

Per concept, `concept_stats.encode_concept` streams the rows through the SAE once. Per pair,
`latent_direction = mean_pos - mean_neg` and `residual_direction` is its image under the decoder's
linear map, `latent_direction @ W_dec`: b_dec cancels in a difference of
decodes, so it is not part of a direction. The seed's script returned `decode(delta)`, which adds
b_dec; `include_decoder_bias=True` reproduces it. Without an SAE `residual_direction.pt` is the plain
residual-space difference of means. Besides the seed's files, every configured direction method
(`steering_core.vectors.methods`: `sae`, `mean_difference`, `sae_top_k`, `probe`, `sae_effect`, `file`) writes
its unit direction with the concepts' mean levels on it (`methods.direction_file`).

Outputs (the seed's layout and keys, plus safetensors/JSON copies):

    <output-root>/layerNN/concepts/<concept>-<hash>.safetensors|.json   streaming statistics per concept file
    <output-root>/layerNN/<pair>/positive_latent_mean.pt, negative_latent_mean.pt, latent_direction.pt,
        residual_direction.pt (each also .safetensors), <method>_direction.safetensors, directions.json
    <output-root>/layerNN/pairwise_stats.pt, pairwise_stats.json

Every direction file and directions.json record `mean_residual_norm` (R, the mean L2 norm of both concepts'
rows: the α unit of the evaluation and the server); the residual direction records `include_decoder_bias`.
"""

from __future__ import annotations

import contextlib
import functools
import json
import logging
import os
from collections.abc import Iterable
from pathlib import Path
from typing import Any, Literal

import torch
from pydantic import Field, field_validator, model_validator

from steering_core.devices import DEVICE_HELP, resolve_device
from steering_core.layout import (
    PAIR_SUMMARY_FILE,
    PAIRWISE_STATS_FILE,
    SLICE_INDEX_FILE,
    STEERING_ROOT,
    check_name,
    layer_dir,
)
from steering_core.pairs import SIDES
from steering_core.remote.locks import output_lock
from steering_core.reporting.progress import ProgressCallback
from steering_core.sae.formats import HOOK_NAME
from steering_core.sae.model import Sae, load_sae
from steering_core.storage.fileio import atomic_dir, atomic_path, read_json, write_json
from steering_core.storage.schema import StrictModel, read_model
from steering_core.tensor_files import load_safetensors, non_finite, require_finite, save_safetensors, save_torch
from steering_core.vectors.concept_stats import (
    FORMAT_VERSION,
    ConceptReader,
    ConceptSource,
    ConceptStats,
    encode_concept,
    read_concept_stats,
)
from steering_core.vectors.methods import METHODS, MethodNames, PairData
from steering_core.vectors.methods.direction_file import (
    MethodDirection,
    method_direction,
    read_method_direction,
    write_method_direction,
)
from steering_core.vectors.methods.supplied import read_supplied
from steering_core.vectors.pair_order import check_slices_order
from steering_core.vectors.pair_slices import check_pair_slices
from steering_core.vectors.report import write_report

logger = logging.getLogger(__name__)
LATENT_MEAN_FILE = "{side}_latent_mean"  # + .pt / .safetensors
LATENT_DIRECTION_FILE = "latent_direction"
RESIDUAL_DIRECTION_FILE = "residual_direction"
MEAN_DIFFERENCE_FILE = "mean_difference_direction"
PAIR_KEY = "{a}__{b}"  # the seed's key of two pairs in pairwise_stats.pt
# the methods written by default: every one that reads only the concepts' statistics and training slices
DEFAULT_METHODS = ("sae", "mean_difference", "sae_top_k", "probe")

class PairSpec(StrictModel):
    """One concept pair of the seed's pairs config (`layer12_pairs.json`)."""

    name: str
    positive_label: str = Field(min_length=1)
    positive_path: str = Field(min_length=1)
    negative_label: str = Field(min_length=1)
    negative_path: str = Field(min_length=1)

    @field_validator("name")
    @classmethod
    def _name_is_a_folder_name(cls, name: str) -> str:
        return check_name(name, "pair name")


class PairsConfig(StrictModel):
    """The seed's pairs config: `{"pairs": [...]}` with unique pair names."""

    pairs: list[PairSpec] = Field(min_length=1)

    @model_validator(mode="after")
    def _unique_names(self) -> PairsConfig:
        names = [pair.name for pair in self.pairs]
        duplicates = sorted({name for name in names if names.count(name) > 1})
        if duplicates:
            raise ValueError(f"pair names must be unique; repeated: {duplicates}")
        return self


# auto: the current directory when the path exists there (the seed's files), else the config's folder
# (the pairs files the pipeline writes); cwd / config force one base.
PathsRelativeTo = Literal["auto", "cwd", "config"]


class SteeringSettings(StrictModel):
    """Everything `compute_steering` needs; defaults are the seed's."""

    pairs_config: Path = Field(description="Pairs JSON, e.g. data/latent_steering/layer12_pairs.json.")
    output_root: Path = Field(Path("data") / STEERING_ROOT, description="Outputs go to <output-root>/layerNN/.")
    layer: int = Field(12, ge=0, description="Decoder layer the concept residuals come from.")
    sae: str | None = Field("gemma-2b-it-res-jb", description=(
        "SAELens folder, .pt/.safetensors state dict, or release name; 'none': residual-space directions only."))
    sae_id: str | None = Field(None, description="SAE within the release (default blocks.<layer>.hook_resid_post).")
    sae_dir: Path | None = Field(
        None, description="Folder holding downloaded release folders, searched before the Hugging Face cache.")
    sae_cfg_from: str | None = Field(
        None, description="For a state-dict SAE: folder or release whose cfg.json applies (as the seed did).")
    device: str = Field("auto", description=DEVICE_HELP)
    batch_size: int = Field(512, gt=0, le=2**20, description="Rows encoded per SAE batch.")
    include_decoder_bias: bool = Field(False, description=(
        "Seed compatibility: residual_direction = decode(delta) = delta @ W_dec + b_dec (default: without b_dec)."))
    top_k: int = Field(20, gt=0, le=4096, description="Latents listed per direction in the report.")
    methods: MethodNames | None = Field(None, description=(
        "Direction methods written per pair (registered in steering_core.vectors.methods); default: "
        + ", ".join(DEFAULT_METHODS) + " (those needing an SAE only when there is one)."))
    direction_file: str | None = Field(None, description=(
        "Method `file`: a safetensors file of one direction per pair and layer ({pair} and {layer} filled in)."))
    probe_folds: int = Field(5, ge=2, le=50, description=(
        "Method `probe`: cross-validation folds, grouped by episode (fewer when fewer training episodes)."))
    probe_c: float | None = Field(None, gt=0, description=(
        "Method `probe`: the inverse L2 strength C (scikit-learn's); default: chosen by cross-validation."))
    effect_min_episodes: int = Field(2, ge=1, le=10_000, description=(
        "Method `sae_effect`: a latent must fire in this many training episodes (1: no vetting; fewer: memorised)."))
    paths_relative_to: PathsRelativeTo = Field("auto", description=(
        "Base of relative concept paths: auto (the current directory when the file exists there, as the seed's "
        "pairs files expect, else the pairs file's folder, as the pipeline writes them), cwd or config."))

    @model_validator(mode="after")
    def _file_method_has_a_file(self) -> SteeringSettings:
        if self.methods is not None and "file" in self.methods and not self.direction_file:
            raise ValueError("methods include `file` but direction_file is not set: name the safetensors file of "
                             "each (pair, layer) direction, e.g. vectors/{pair}_layer{layer}.safetensors")
        return self

    def method_list(self, has_sae: bool) -> tuple[str, ...]:
        """Return the methods to write: the configured ones (ValueError for one needing an absent SAE), or the
        defaults, without the SAE's when there is none."""
        if self.methods is None:
            return tuple(name for name in DEFAULT_METHODS if has_sae or not METHODS[name].needs_sae)
        missing = [name for name in self.methods if METHODS[name].needs_sae and not has_sae]
        if missing:
            raise ValueError(f"layer {self.layer}: steering.methods {list(self.methods)}: {missing} need an SAE and "
                             "sae is none; drop them or name an SAE")
        return self.methods


def read_pairs_config(path: str | os.PathLike) -> PairsConfig:
    """Return the pairs config at `path` (the seed's format, read unchanged)."""
    return read_model(path, PairsConfig, what="pairs config")


def resolve_concept_path(path: str, config_path: Path, relative_to: PathsRelativeTo = "auto") -> Path:
    """Return a pairs file's concept path: absolute as given, else against cwd or the config's folder.

    `auto` takes the current directory when the file exists there (the seed's cwd-relative files), else
    the config's folder (pairs files written by the pipeline), and logs which base it used.
    """
    given = Path(path).expanduser()
    if given.is_absolute():
        return given
    if relative_to == "cwd" or (relative_to == "auto" and given.exists()):
        base = Path.cwd()
    else:
        base = config_path.parent
    if relative_to == "auto":
        logger.info("%s: %s resolved against %s", config_path, path, "the current directory" if base == Path.cwd()
                    else f"the pairs file's folder {base}")
    return base / given


def concept_sources(
    config: PairsConfig, config_path: Path, relative_to: PathsRelativeTo = "auto"
) -> tuple[dict[Path, ConceptSource], dict[str, tuple[Path, Path]]]:
    """Return (unique concept files, pair -> (positive file, negative file)), see `resolve_concept_path`."""
    sources: dict[Path, ConceptSource] = {}
    pairs: dict[str, tuple[Path, Path]] = {}
    for pair in config.pairs:
        files = []
        for side in SIDES:
            path = resolve_concept_path(getattr(pair, f"{side}_path"), config_path, relative_to)
            sources.setdefault(path, ConceptSource(getattr(pair, f"{side}_label"), path))
            files.append(path)
        pairs[pair.name] = (files[0], files[1])
    return sources, pairs


def check_concepts(
    sources: dict[Path, ConceptSource], pairs: dict[str, tuple[Path, Path]], sae: Sae | None
) -> dict[Path, ConceptReader]:
    """Return an open reader per concept file; raise once listing every missing or unusable file."""
    users = {
        path: [f"{name}.{side}_path" for name, files in pairs.items() for side, f in zip(SIDES, files, strict=True)
               if f == path]
        for path in sources
    }
    readers, missing, problems = {}, [], []
    for path in sources:
        where = f"{path} ({', '.join(users[path])})"
        if not path.is_file():
            missing.append(f"{where}: file not found")
            continue
        try:
            reader = ConceptReader(path)
        except ValueError as err:
            problems.append(f"{where}: {str(err).removeprefix(f'{path}: ')}")
            continue
        expected = f"(rows, {sae.cfg.d_in})" if sae is not None else "(rows, d_in)"
        if not reader.valid_shape:
            problems.append(f"{where}: tensor is {reader.shape}, expected {expected}")
        elif reader.dtype is None or not reader.dtype.is_floating_point:
            problems.append(f"{where}: dtype is {reader.dtype or 'not a float'}, expected a floating-point tensor")
        elif reader.rows == 0:
            problems.append(f"{where}: no rows; the concept is empty, re-run slicing or drop the pair")
        elif sae is not None and reader.width != sae.cfg.d_in:
            problems.append(
                f"{where}: residuals are {reader.shape} but SAE {sae.name} expects (*, {sae.cfg.d_in}); "
                f"use residuals of the layer and model the SAE was trained on, or another --sae"
            )
        elif (bad := _non_finite_rows(reader)) is not None:
            problems.append(f"{where}: {bad}; re-run slice (and capture) to rewrite it")
        readers[path] = reader
    widths = {reader.width for reader in readers.values() if reader.valid_shape}
    if sae is None and len(widths) > 1:
        problems.append(f"concept files have different widths {sorted(widths)}; all must come from one layer")
    if missing or problems:
        kind = FileNotFoundError if missing else ValueError
        hint = "; relative paths are resolved against the base directory (see --paths-relative-to)" if missing else ""
        raise kind("unusable concept files" + hint + ": " + "; ".join(missing + problems))
    return readers


def _non_finite_rows(reader: ConceptReader, batch_size: int = 8192) -> str | None:
    """Return `non_finite`'s message for the first rows of a concept file holding NaN or Inf, else None.

    Read once before any output is written, so a bad file leaves nothing half-done (the SAE pass, far
    slower than this read, then finds the file's pages cached).
    """
    for number, batch in enumerate(reader.batches(batch_size)):
        if (problem := non_finite(batch, "residuals", number * batch_size)) is not None:
            return problem
    return None


def compute_pair(
    pair: PairSpec,
    positive_stats: Path,
    negative_stats: Path,
    layer_path: Path,
    sae: Sae | None,
    settings: SteeringSettings,
) -> Path:
    """Write one pair's direction files from its two concept statistics; return the pair folder.

    Besides the seed's files, every method of `settings.method_list` writes `<method>_direction.safetensors`
    (`methods.direction_file`), listed under `methods` in directions.json; all are computed before anything is
    written, so a method that fails leaves the pair folder as it was.
    """
    include_decoder_bias = settings.include_decoder_bias
    stats = dict(zip(SIDES, (read_concept_stats(positive_stats), read_concept_stats(negative_stats)), strict=True))
    counts = {side: stats[side].count for side in SIDES}
    head = {"pair": pair.name, "positive_concept": pair.positive_label, "negative_concept": pair.negative_label,
            "reduce": {side: slice_reduction(stats[side].path) for side in SIDES},
            "mean_residual_norm": mean_residual_norm(stats.values())}
    bias = include_decoder_bias and sae is not None
    methods = pair_methods(pair.name, stats, sae, settings, head["mean_residual_norm"])
    mean_difference = (stats["positive"].residual_mean - stats["negative"].residual_mean).float()
    summary: dict[str, Any] = {
        "format_version": FORMAT_VERSION,
        **head,
        "counts": counts,
        "sae": sae.describe() if sae is not None else None,
        "method": "sae_decoder" if sae is not None else "mean_difference",
        "include_decoder_bias": bias,
        "direction_space": _direction_space(sae),
        "mean_difference_norm": float(mean_difference.norm()),
        "concepts": {
            side: {"label": stats[side].label, "stats": os.path.relpath(path, layer_path / pair.name),
                   "fvu": stats[side].fvu, "mean_l0": stats[side].mean_l0}
            for side, path in zip(SIDES, (positive_stats, negative_stats), strict=True)
        },
        "files": {},
    }
    with contextlib.ExitStack() as stack:
        staging = stack.enter_context(atomic_dir(layer_path / pair.name, overwrite=True))
        staging.mkdir(parents=True)
        write = functools.partial(_write_tensor_dict, staging, layer_path / pair.name, summary["files"])
        if sae is None:
            write(RESIDUAL_DIRECTION_FILE, "residual_direction",
                  {**head, "residual_direction": mean_difference, "residual_norm": float(mean_difference.norm()),
                   "counts": counts, "include_decoder_bias": False})
        else:
            for side in SIDES:
                write(LATENT_MEAN_FILE.format(side=side), "mean",
                      {"concept": getattr(pair, f"{side}_label"), "count": counts[side],
                       "mean": stats[side].latent_mean.float()})
            latent = (stats["positive"].latent_mean - stats["negative"].latent_mean).float()
            residual = sae.decode_direction(latent).cpu()
            if include_decoder_bias:
                residual = residual + sae.b_dec.cpu()
            residual = residual.float()
            write(LATENT_DIRECTION_FILE, "latent_direction",
                  {**head, "latent_direction": latent, "latent_norm": float(latent.norm()), "counts": counts})
            write(RESIDUAL_DIRECTION_FILE, "residual_direction",
                  {**head, "residual_direction": residual, "residual_norm": float(residual.norm()), "counts": counts,
                   "include_decoder_bias": bias})
            summary |= {
                "latent_norm": float(latent.norm()),
                "residual_norm": float(residual.norm()),
                "decoded_vs_mean_difference_cosine": cosine(residual, mean_difference),
            }
        summary["methods"] = {direction.method: direction.entry(write_method_direction(staging, direction))
                              for direction in methods}
        write_json(staging / PAIR_SUMMARY_FILE, summary)
    logger.info("%s: wrote %s and the methods %s", pair.name, ", ".join(sorted(summary["files"])),
                ", ".join(summary["methods"]))
    return layer_path / pair.name


def check_methods(settings: SteeringSettings, pairs: Iterable[str], width: int, has_sae: bool) -> None:
    """Raise one ValueError for methods that cannot run: one needing an absent SAE, or a supplied `file` direction
    of a pair that is missing, unreadable, of another width than `width`, non-finite or zero."""
    names = settings.method_list(has_sae)
    if "file" not in names:
        return
    problems = []
    for pair in pairs:
        try:
            read_supplied(settings.direction_file, pair, settings.layer, width)
        except ValueError as err:
            problems.append(str(err))
    if problems:
        raise ValueError("; ".join(problems))


def pair_methods(pair: str, stats: dict[str, ConceptStats], sae: Sae | None, settings: SteeringSettings,
                 residual_norm: float | None) -> list[MethodDirection]:
    """Return the unit direction of every method of `settings` for one pair (nothing written)."""
    data = PairData(pair, settings.layer, stats, (stats["positive"].path, stats["negative"].path), sae, settings)
    out = []
    for name in settings.method_list(sae is not None):
        result = METHODS[name].compute(data)
        out.append(method_direction(name, pair, settings.layer, result.direction, stats, residual_norm, result.record))
    return out


def mean_residual_norm(stats: Iterable[ConceptStats]) -> float | None:
    """Return the mean L2 norm of every row of the concepts (R, the evaluation's and server's α unit);
    None when a statistics file predates the recorded norm sums."""
    stats = list(stats)
    if any(item.residual_norm_sum is None for item in stats):
        return None
    return sum(item.residual_norm_sum for item in stats) / sum(item.count for item in stats)


def slice_reduction(concept_file: Path) -> str | None:
    """Return how a concept file's rows were cut: "token" (one per instruction token) or "frame" (the seed's).

    Read from the slices' index.json beside the file; None when there is none (e.g. slices made by the seed).
    """
    index = Path(concept_file).parent / SLICE_INDEX_FILE
    if not index.is_file():
        return None
    try:
        reduce = read_json(index).get("settings", {}).get("reduce")
    except (ValueError, AttributeError):
        return None
    return reduce if isinstance(reduce, str) else None


def compute_pairwise_stats(layer_path: Path, pair_names: list[str]) -> Path:
    """Write cosines and norms of every two pairs' directions (the seed's pairwise_stats.pt); return the .pt path."""
    vectors = {name: read_pair_vectors(layer_path / name) for name in pair_names}
    sae_used = all("latent" in vectors[name] for name in pair_names)
    entries, extras = {}, {}
    for i, a in enumerate(pair_names):
        for b in pair_names[i + 1:]:
            va, vb = vectors[a], vectors[b]
            entry = {}
            if sae_used:
                entry["latent_cosine"] = cosine(va["latent"], vb["latent"])
            entry["residual_cosine"] = cosine(va["residual"], vb["residual"])
            if sae_used:
                entry |= {"latent_norm_a": float(va["latent"].norm()), "latent_norm_b": float(vb["latent"].norm())}
            if sae_used and "mean" in va and "mean" in vb:
                extras[PAIR_KEY.format(a=a, b=b)] = {"mean_difference_cosine": cosine(va["mean"], vb["mean"])}
            entry |= {"residual_norm_a": float(va["residual"].norm()), "residual_norm_b": float(vb["residual"].norm())}
            entries[PAIR_KEY.format(a=a, b=b)] = entry
    pt_path = layer_path / f"{PAIRWISE_STATS_FILE}.pt"
    with atomic_path(pt_path) as tmp:
        save_torch(entries, tmp)
    write_json(pt_path.with_suffix(".json"), {
        "format_version": FORMAT_VERSION,
        "pairs": pair_names,
        "sae_used": sae_used,
        "entries": {key: entry | extras.get(key, {}) for key, entry in entries.items()},
    })
    return pt_path


def cosine(a: torch.Tensor, b: torch.Tensor) -> float:
    """Return the cosine of two vectors in float64 (0 when one is zero, as torch's cosine_similarity)."""
    return float(torch.nn.functional.cosine_similarity(a.double().flatten(), b.double().flatten(), dim=0))


def load_steering_sae(settings: SteeringSettings) -> Sae | None:
    """Return the SAE named by the settings on the chosen device, checked against the layer (None: no SAE)."""
    if settings.sae is None:
        return None
    sae = load_sae(
        settings.sae,
        settings.sae_id or HOOK_NAME.format(layer=settings.layer),
        resolve_device(settings.device),
        local_dir=settings.sae_dir,
        cfg_from=settings.sae_cfg_from,
    )
    check_sae_layer(sae, settings.layer)
    if settings.top_k > sae.cfg.d_sae:
        raise ValueError(f"top_k {settings.top_k}: more latents than SAE {sae.name} has ({sae.cfg.d_sae}); "
                         f"list at most {sae.cfg.d_sae}")
    return sae


def check_sae_layer(sae: Sae, layer: int) -> None:
    """Raise if the SAE's hook names another layer than the residuals' (unknown hooks pass)."""
    if sae.cfg.hook_layer is not None and sae.cfg.hook_layer != layer:
        raise ValueError(
            f"SAE {sae.name} reads {sae.cfg.hook_name} (layer {sae.cfg.hook_layer}) but layer {layer} "
            f"was requested; pass the SAE of layer {layer}, or no SAE for residual-space directions"
        )


def compute_steering(settings: SteeringSettings, *, sae: Sae | None = None, progress: ProgressCallback | None = None) -> Path:
    """Run every step for one layer; return the layer folder.

    Steps: concept statistics, pair directions, pairwise stats, report. A pair whose slices do not match its labels
    and the layer (`pair_slices.check_pair_slices`), or whose slices' manifest lists its concepts the other way
    round (`pair_order.check_slices_order`), is refused first.

    Relative concept paths resolve as `resolve_concept_path` says. A preloaded `sae` overrides `settings.sae`.
    The layer folder is locked meanwhile: a second run on it waits, then reuses the statistics (the SAE pass).
    """
    config = read_pairs_config(settings.pairs_config)
    sources, pairs = concept_sources(config, settings.pairs_config, settings.paths_relative_to)
    check_pair_slices([(pair.name, (pair.positive_label, pair.negative_label), pairs[pair.name])
                       for pair in config.pairs], settings.layer, settings.pairs_config)
    for pair in config.pairs:
        check_slices_order(pair.name, (pair.positive_label, pair.negative_label), pairs[pair.name],
                           settings.pairs_config)
    if sae is None:
        sae = load_steering_sae(settings)
    else:
        check_sae_layer(sae, settings.layer)
    readers = check_concepts(sources, pairs, sae)
    check_methods(settings, pairs, next(iter(readers.values())).width, sae is not None)
    layer_path = settings.output_root / layer_dir(settings.layer)
    with output_lock(layer_path):  # a second run waits, then reuses the concept statistics written here
        rows = {path: reader.rows for path, reader in readers.items()}  # progress counts rows over every concept
        total, done = sum(rows.values()), 0
        stats_files = {}
        for path, source in sources.items():
            def advance(step: int, _: int, before: int = done) -> None:
                if progress is not None:
                    progress(before + step, total)

            stats_files[path] = encode_concept(
                source, layer_path, sae, batch_size=settings.batch_size, reader=readers[path], progress=advance
            )
            done += rows[path]
            advance(0, total, before=done)
        for pair in config.pairs:
            positive, negative = pairs[pair.name]
            compute_pair(pair, stats_files[positive], stats_files[negative], layer_path, sae, settings)
        compute_pairwise_stats(layer_path, [pair.name for pair in config.pairs])
        write_report(layer_path, top_k=settings.top_k)
    return layer_path


def _direction_space(sae: Sae | None) -> str:
    """Return where the residual direction lives: raw residuals, or the SAE's normalised input space."""
    if sae is None or sae.cfg.normalize_activations in ("none", "expected_average_only_in"):
        return "residual"
    if sae.cfg.normalize_activations == "constant_norm_rescale":
        return "normalised inputs: x * sqrt(d_in) / ||x|| per row; divide by that factor for a given row"
    return "normalised inputs: (x - mean) / (std + 1e-5) per row; multiply by that row's std"


def _write_tensor_dict(
    folder: Path, target: Path, files: dict[str, str], stem: str, tensor_key: str, payload: dict
) -> None:
    """Write `payload` as `<stem>.pt` (the seed's dict) and its tensor as `<stem>.safetensors` with JSON metadata.

    `folder` is the staging folder of `target`. A tensor holding NaN or Inf is refused, naming its file in
    `target`, before it is written (the staging folder is then dropped).
    """
    require_finite(payload[tensor_key], target / f"{stem}.safetensors", tensor_key,
                   "the concept statistics or the SAE overflowed; check their values")
    save_torch(payload, folder / f"{stem}.pt")
    metadata = {key: json.dumps(value) for key, value in payload.items() if key != tensor_key}
    save_safetensors({tensor_key: payload[tensor_key].contiguous()}, folder / f"{stem}.safetensors", metadata=metadata)
    files[stem] = {"pt": f"{stem}.pt", "safetensors": f"{stem}.safetensors", "tensor": tensor_key}


def read_pair_vectors(pair_path: Path) -> dict[str, torch.Tensor]:
    """Return a pair's directions from its safetensors copies: residual, and latent + mean when an SAE was used."""
    files = read_json(pair_path / PAIR_SUMMARY_FILE)["files"]

    def vector(stem: str) -> torch.Tensor:
        path, key = pair_path / files[stem]["safetensors"], files[stem]["tensor"]
        tensor = load_safetensors(path)[key]
        require_finite(tensor, path, key, "re-run steer to rewrite the pair's directions")
        return tensor

    vectors = {"residual": vector(RESIDUAL_DIRECTION_FILE)}
    if LATENT_DIRECTION_FILE in files:
        vectors["latent"] = vector(LATENT_DIRECTION_FILE)
    methods = read_json(pair_path / PAIR_SUMMARY_FILE).get("methods") or {}
    if "mean_difference" in methods:
        vectors["mean"] = read_method_direction(pair_path / methods["mean_difference"]["file"]).direction
    return vectors
