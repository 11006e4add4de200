"""One static HTML page per layer for browsing an SAE's features: a single file, no server, no external URL.

For the latents of each pair's top-k (largest |latent_direction|) and the most active latents overall
(largest mean activation over the scanned rows), the page shows the top-activating frames (the agentview
thumbnail as an inline JPEG, the instruction with every token shaded by its activation and the peak token
outlined, episode, frame and dataset index), an inline SVG histogram of the latent's activations, its firing
frequency, and per pair its rank in the pair's top-k and the cosine of its decoder row with the pair's
residual direction. Everything is embedded (data: URIs, inline CSS, no script), so the file opens from disk.
"""

from __future__ import annotations

import base64
import html
import logging
from collections.abc import Callable, Collection, Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from steering_core.layout import PAIR_SUMMARY_FILE, PAIRWISE_STATS_FILE
from steering_core.sae.model import Sae
from steering_core.sae_quality.feature_scan import FeatureScan, FrameContext, RowBatch, example_frames, frame_contexts
from steering_core.storage.fileio import read_json, write_text
from steering_core.vectors.directions import read_pair_vectors

logger = logging.getLogger(__name__)

RowsOfEpisodes = Callable[[Collection[int]], Iterable[RowBatch]]  # episodes -> their rows, e.g. RowSource.sequential
TokenText = Callable[[int], str]  # token id -> its text
THUMBNAIL_KEY = "image"  # LIBERO's agentview camera (steering_core.pi05.preprocess.LIBERO_IMAGE_KEYS[0])
WORD_BOUNDARY = "\u2581"  # SentencePiece's word-start mark, shown as a space
MEMBER, PEAK = ' class="member"', ' class="peak"'  # a pair the latent is in; the token where it peaks


@dataclass(frozen=True)
class PairLatents:
    """One steering pair: its top-k latents by |latent_direction| and its residual direction (d_in,)."""

    pair: str
    latents: tuple[int, ...]
    values: tuple[float, ...]  # latent_direction at those latents
    residual_direction: torch.Tensor


def sentencepiece_text(tokenizer_path: Path) -> TokenText:
    """Return token id -> piece of a SentencePiece model (the prompt tokenizer's `tokenizer.model`)."""
    import sentencepiece  # deferred, as in steering_core.pi05.tokenizer

    return sentencepiece.SentencePieceProcessor(model_file=str(tokenizer_path)).id_to_piece


def read_pair_latents(steering_layer: Path, top_k: int, sae: Sae) -> list[PairLatents]:
    """Return every pair of a steering layer folder (`latent_steering/layerNN`), in pairwise_stats order.

    A pair steered through another SAE than `sae` (its directions.json records other weights) keeps its
    residual direction but lists no latents: its latent indices name another SAE's latents.
    """
    pairs = []
    for name in read_json(steering_layer / f"{PAIRWISE_STATS_FILE}.json")["pairs"]:
        vectors = read_pair_vectors(steering_layer / name)
        recorded = (read_json(steering_layer / name / PAIR_SUMMARY_FILE).get("sae") or {}).get("weights_sha256")
        same_sae = recorded is None or sae.weights_sha256 is None or recorded == sae.weights_sha256
        latents, values = (), ()
        if "latent" in vectors and same_sae:
            direction = vectors["latent"].float()
            order = torch.argsort(direction.abs(), descending=True, stable=True)[:top_k]
            latents, values = tuple(int(i) for i in order), tuple(float(direction[i]) for i in order)
        elif "latent" in vectors:
            logger.info("%s: steered through another SAE (weights %s); its latents are not listed", name, recorded)
        pairs.append(PairLatents(name, latents, values, vectors["residual"].float()))
    return pairs


def read_thumbnails(
    dataset_root: Path, repo_id: str, frames: dict[int, int], *, size: int = 112, video_backend: str | None = None
) -> dict[int, str]:
    """Return dataset index -> a `data:image/jpeg` URI of its agentview frame, `size` pixels square.

    `frames` maps each dataset index to its episode; only those episodes are read.
    """
    from torchvision.io import encode_jpeg

    from steering_core.capture.frames import FrameDataset, frame_source, position_columns
    from steering_core.data.dataset import read_meta

    if not frames:
        return {}
    meta = read_meta(dataset_root)
    dataset = frame_source(meta, repo_id, sorted(set(frames.values())), video_backend)
    position = {int(index): p for p, index in enumerate(position_columns(dataset)[1])}
    missing = sorted(index for index in frames if index not in position)
    if missing:
        raise ValueError(f"{dataset_root}: frames with index {missing[:5]} are not in the dataset; the residual run "
                         "was captured from another dataset")
    checked = FrameDataset(dataset, (THUMBNAIL_KEY,), meta)  # a bad camera: one line naming its file and frame
    uris = {}
    for index in frames:
        image = checked[position[index]][THUMBNAIL_KEY].float()  # (3, H, W) in [0, 1]
        image = torch.nn.functional.interpolate(image[None], size=(size, size), mode="bilinear", antialias=True)[0]
        jpeg = encode_jpeg((image.clamp(0, 1) * 255).round().to(torch.uint8), quality=85)
        uris[index] = "data:image/jpeg;base64," + base64.b64encode(jpeg.numpy().tobytes()).decode("ascii")
    return uris


def page_latents(scan: FeatureScan, pairs: Sequence[PairLatents], most_active: int) -> list[int]:
    """Return the latents a page shows: each pair's top-k in order, then the most active ones, without repeats."""
    chosen = [latent for pair in pairs for latent in pair.latents] + scan.most_active(most_active)
    return list(dict.fromkeys(chosen))


def write_feature_page(
    path: Path,
    scan: FeatureScan,
    sae: Sae,
    rows: RowsOfEpisodes,
    *,
    steering_layer: Path | None = None,
    dataset_root: Path | None = None,
    repo_id: str | None = None,
    token_text: TokenText | None = None,
    pair_top_k: int = 10,
    most_active: int = 20,
    examples: int = 8,
    title: str | None = None,
    video_backend: str | None = None,
) -> Path:
    """Write the feature page of one layer to `path` (atomically); return it.

    Args:
        scan: `scan_features` of `sae` over the layer's rows.
        rows: episodes -> row batches of those episodes (the second pass reads only the examples' episodes).
        steering_layer: the layer's steering folder (pairs and their directions); None: most active latents only.
        dataset_root, repo_id: the LeRobot dataset the rows were captured from, for thumbnails (None: none).
        token_text: token id -> text (`PromptTokenizer.piece`-like); None shows the ids.
    """
    pairs = read_pair_latents(steering_layer, pair_top_k, sae) if steering_layer is not None else []
    latents = page_latents(scan, pairs, most_active)
    wanted = example_frames(scan, latents, examples)
    episodes = {e["index"]: e["episode_index"] for latent in latents for e in scan.examples(latent)[:examples]}
    contexts = frame_contexts(rows(sorted(set(episodes.values()))), sae, wanted) if wanted else {}
    thumbnails = {}
    if dataset_root is not None and repo_id is not None:
        thumbnails = read_thumbnails(dataset_root, repo_id, episodes, video_backend=video_backend)
    decoder = sae.W_dec.detach().float().cpu()
    body = [_header(scan, sae, title, pairs, latents, scan.most_active(most_active))]
    body += [_latent_section(scan, latent, pairs, decoder, contexts, thumbnails, token_text, examples)
             for latent in latents]
    write_text(path, _document(title or f"Features of {sae.name}", "\n".join(body)))
    logger.info("feature page of %d latents written to %s", len(latents), path)
    return Path(path)


def token_strings(token_ids: Iterable[int], token_text: TokenText | None) -> list[str]:
    """Return each token's display text (SentencePiece's word mark as a space; `#id` without a tokenizer)."""
    if token_text is None:
        return [f"#{int(token)} " for token in token_ids]
    return [token_text(int(token)).replace(WORD_BOUNDARY, " ") for token in token_ids]


def decoder_cosines(decoder: torch.Tensor, latent: int, pairs: Sequence[PairLatents]) -> list[float]:
    """Return the cosine of the latent's decoder row (d_in,) with each pair's residual direction."""
    row = decoder[latent].double()
    return [float(torch.nn.functional.cosine_similarity(row, pair.residual_direction.double(), dim=0))
            for pair in pairs]


def histogram_svg(edges: np.ndarray, counts: np.ndarray, width: int = 260, height: int = 70) -> str:
    """Return an inline SVG bar chart of a histogram, labelled with its range and largest count."""
    peak = max(int(counts.max()), 1) if counts.size else 1
    bar = width / max(len(counts), 1)
    bars = "".join(
        f'<rect x="{i * bar:.1f}" y="{height - 14 - (height - 24) * c / peak:.1f}" width="{max(bar - 1, 1):.1f}" '
        f'height="{(height - 24) * c / peak:.1f}" fill="#3b6fb6"/>'
        for i, c in enumerate(counts) if c
    )
    labels = (f'<text x="0" y="{height - 2}">0</text>'
              f'<text x="{width}" y="{height - 2}" text-anchor="end">{edges[-1]:.3g}</text>'
              f'<text x="0" y="9">{peak} rows</text>')
    return (f'<svg class="hist" width="{width}" height="{height}" '
            f'viewBox="0 0 {width} {height}" role="img">{bars}{labels}</svg>')


def _header(
    scan: FeatureScan, sae: Sae, title: str | None, pairs: Sequence[PairLatents], latents: list[int], active: list[int]
) -> str:
    rows = "".join(
        f"<tr><td>{html.escape(pair.pair)}</td><td>"
        + " ".join(f'<a href="#latent-{latent}">{latent}</a>' for latent in pair.latents)
        + "</td></tr>"
        for pair in pairs
    )
    pair_table = f"<table><tr><th>pair</th><th>top latents by |latent direction|</th></tr>{rows}</table>" if rows else ""
    links = " ".join(f'<a href="#latent-{latent}">{latent}</a>' for latent in active)
    return (f"<h1>{html.escape(title or f'Features of {sae.name}')}</h1>"
            f"<p>SAE <code>{html.escape(sae.name)}</code>: {scan.d_sae} latents, scanned over {scan.rows} rows of "
            f"{scan.frames} frames; {len(latents)} latents shown.</p>{pair_table}"
            f"<p>Most active (mean activation per row): {links}</p>")


def _latent_section(
    scan: FeatureScan, latent: int, pairs: Sequence[PairLatents], decoder: torch.Tensor,
    contexts: dict[int, FrameContext], thumbnails: dict[int, str], token_text: TokenText | None, examples: int,
) -> str:
    frequency, shown = scan.frequency()[latent], scan.examples(latent)[:examples]
    top = shown[0]["value"] if shown else 0.0
    cosines = decoder_cosines(decoder, latent, pairs)
    pair_rows = "".join(
        f"<tr{MEMBER if latent in pair.latents else ''}><td>{html.escape(pair.pair)}</td>"
        f"<td>{_rank(pair, latent)}</td><td>{cosine:+.3f}</td></tr>"
        for pair, cosine in zip(pairs, cosines, strict=True)
    )
    pair_table = (f"<table><tr><th>pair</th><th>rank in top-k (value)</th><th>decoder cos with residual "
                  f"direction</th></tr>{pair_rows}</table>") if pair_rows else ""
    cards = "".join(_example_card(example, latent, contexts.get(example["index"]), thumbnails.get(example["index"]),
                                  token_text) for example in shown) or "<p>never fires on the scanned rows</p>"
    return (f'<section id="latent-{latent}"><h2>Latent {latent}</h2>'
            f"<p>fires on {frequency:.2%} of rows; mean activation {scan.mean_activation()[latent]:.4g}; "
            f"max {top:.4g}</p><div class=\"row\">{histogram_svg(*scan.histogram(latent))}{pair_table}</div>"
            f'<div class="examples">{cards}</div></section>')


def _rank(pair: PairLatents, latent: int) -> str:
    if latent not in pair.latents:
        return "&ndash;"
    rank = pair.latents.index(latent)
    return f"{rank + 1} ({pair.values[rank]:+.3g})"


def _example_card(
    example: dict, latent: int, context: FrameContext | None, thumbnail: str | None, token_text: TokenText | None
) -> str:
    image = (f'<img src="{thumbnail}" alt="agentview, index {example["index"]}" width="112" height="112">'
             if thumbnail else '<div class="noimage">no frame</div>')
    if context is None:
        tokens = token_strings([example["token_id"]], token_text)
        text = f'<mark class="peak">{html.escape(tokens[0])}</mark>'
    else:
        values = context.values(latent)
        scale = max(float(values.max()), 1e-12)
        text = "".join(
            f'<mark{PEAK if position == example["token_position"] else ""} '
            f'style="background: rgba(230, 120, 20, {max(value, 0.0) / scale:.2f})" title="{value:.4g}">'
            f"{html.escape(piece)}</mark>"
            for position, value, piece in zip(context.token_position, values,
                                              token_strings(context.token_id, token_text), strict=True)
        )
    return (f'<figure class="example">{image}<figcaption><b>{example["value"]:.4g}</b> · episode '
            f'{example["episode_index"]} · frame {example["frame_index"]} · index {example["index"]}'
            f'<div class="tokens">{text}</div></figcaption></figure>')


_STYLE = """
body { font: 14px/1.4 system-ui, sans-serif; margin: 1.5em; color: #222; }
section { border-top: 1px solid #ccc; padding-top: .5em; margin-top: 1em; }
table { border-collapse: collapse; margin: .3em 1em .3em 0; }
td, th { border: 1px solid #ddd; padding: 2px 6px; text-align: left; }
tr.member { background: #fff3d6; }
.row { display: flex; flex-wrap: wrap; align-items: flex-start; gap: 1em; }
.hist text { font-size: 9px; fill: #555; }
.examples { display: flex; flex-wrap: wrap; gap: .6em; }
figure.example { margin: 0; width: 230px; display: flex; gap: 6px; font-size: 12px; }
figure.example img, .noimage { width: 112px; height: 112px; flex: none; background: #eee; }
.tokens { margin-top: 3px; white-space: pre-wrap; }
mark { color: inherit; background: none; }
mark.peak { outline: 2px solid #c0392b; }
"""


def _document(title: str, body: str) -> str:
    return (f'<!DOCTYPE html><html lang="en"><head><meta charset="utf-8"><title>{html.escape(title)}</title>'
            f'<link rel="icon" href="data:,"><style>{_STYLE}</style></head><body>{body}</body></html>\n')
