"""The feature browser: the streaming feature scan, the static HTML page (in headless Chromium) and the Neuronpedia export."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from steering_core.capture.shards import ROW_COLUMNS, open_shard, read_run_metadata
from steering_core.sae.feature_scan import frame_contexts, read_feature_scan, scan_features
from steering_core.sae.formats import SaeConfig
from steering_core.sae.model import StandardSae, TopKSae

D_IN, D_SAE = 8, 24


def make_sae(kind: str = "standard", seed: int = 0) -> StandardSae | TopKSae:
    """A random tiny SAE (d_in 8, d_sae 24) whose latents fire on roughly half the rows."""
    g = torch.Generator().manual_seed(seed)
    weights = {"W_enc": torch.randn(D_IN, D_SAE, generator=g), "b_enc": torch.randn(D_SAE, generator=g) * 0.5,
               "W_dec": torch.randn(D_SAE, D_IN, generator=g), "b_dec": torch.zeros(D_IN)}
    if kind == "topk":
        return TopKSae(SaeConfig(d_in=D_IN, d_sae=D_SAE, architecture="topk", k=4, source="tiny"), weights)
    return StandardSae(SaeConfig(d_in=D_IN, d_sae=D_SAE, source="tiny"), weights)


def make_rows(frames: int = 40, seed: int = 1) -> tuple[torch.Tensor, dict[str, np.ndarray]]:
    """Rows of `frames` frames with 1-5 tokens each, sorted by (index, token_position) as in a shard."""
    rng = np.random.default_rng(seed)
    tokens = rng.integers(1, 6, size=frames)
    index = np.repeat(np.arange(100, 100 + frames), tokens)
    columns = {
        "index": index,
        "episode_index": index // 10,
        "frame_index": index % 10,
        "token_position": np.concatenate([np.arange(n) + 3 for n in tokens]),
        "token_id": rng.integers(5, 50, size=len(index)),
    }
    rows = torch.from_numpy(rng.standard_normal((len(index), D_IN)).astype(np.float32))
    rows[rng.integers(0, len(index), size=5)] *= 6  # a few large activations widen the histograms
    return rows, columns


def batched(rows: torch.Tensor, columns: dict[str, np.ndarray], size: int):
    for start in range(0, len(rows), size):
        yield rows[start : start + size], {name: values[start : start + size] for name, values in columns.items()}


def shard_batches(run_dir: Path, layer: int, episodes=None, size: int = 64):
    """(rows, columns) batches of a capture run's layer, as `RowSource.sequential` yields them."""
    for record in read_run_metadata(run_dir).layer_shards(layer):
        if episodes is not None and not set(record.episodes) & set(episodes):
            continue
        with open_shard(run_dir / record.file) as shard:
            rows, columns = shard.residuals().float(), shard.columns(ROW_COLUMNS)
        keep = np.isin(columns["episode_index"], list(record.episodes if episodes is None else episodes))
        yield from batched(rows[torch.from_numpy(keep)], {k: v[keep] for k, v in columns.items()}, size)


def naive_scan(sae, rows, columns, top_n: int, bins: int):
    """Per-latent top frames, histograms and counts from the dense activations, one latent and frame at a time."""
    acts = sae.encode(rows).numpy().astype(np.float64)
    top, hist = {}, {}
    for latent in range(D_SAE):
        candidates = []
        for index in np.unique(columns["index"]):
            members = np.flatnonzero(columns["index"] == index)
            best = members[np.argmax(acts[members, latent])]  # argmax takes the first of equal values
            if acts[best, latent] > 0:
                candidates.append((-acts[best, latent], index, best))
        candidates.sort()
        top[latent] = [(-neg, {name: int(columns[name][row]) for name in ROW_COLUMNS})
                       for neg, _, row in candidates[:top_n]]
        fired = acts[:, latent][acts[:, latent] > 0]
        if fired.size:
            high = 2.0 ** np.floor(np.log2(fired.max()) + 1)  # smallest power of two above every value
            hist[latent] = (high, np.histogram(fired, bins=bins, range=(0, high))[0])
    return acts, top, hist


@pytest.mark.parametrize("kind", ["standard", "topk"])
def test_feature_scan_matches_a_dense_per_latent_reference_whatever_the_batching(kind, tmp_path):
    sae = make_sae(kind)
    rows, columns = make_rows()
    acts, top, hist = naive_scan(sae, rows, columns, top_n=5, bins=8)
    results = [scan_features(batched(rows, columns, size), sae, top_n=5, bins=8) for size in (1, 3, 7, len(rows))]
    for scan in results:
        assert scan.rows == len(rows) and scan.frames == 40
        np.testing.assert_array_equal(scan.firing, (acts > 0).sum(axis=0))
        np.testing.assert_allclose(scan.activation_sum, acts.sum(axis=0), rtol=1e-5)
        for latent in range(D_SAE):
            examples = scan.examples(latent)
            assert [{k: v for k, v in e.items() if k != "value"} for e in examples] == [c for _, c in top[latent]]
            np.testing.assert_allclose([e["value"] for e in examples], [v for v, _ in top[latent]], rtol=1e-6)
            if latent in hist:
                edges, counts = scan.histogram(latent)
                assert edges[-1] == hist[latent][0]
                np.testing.assert_array_equal(counts, hist[latent][1])
            else:
                assert scan.histogram(latent)[1].sum() == 0
    assert any(len(top[latent]) == 5 for latent in range(D_SAE)) and len(hist) > D_SAE // 2
    scan = results[0]
    assert scan.most_active(3) == list(np.argsort(-acts.sum(axis=0), kind="stable")[:3])
    again = read_feature_scan(scan.write(tmp_path / "scan.safetensors"))
    assert again.examples(7) == scan.examples(7) and again.rows == scan.rows and again.sae == "tiny"
    np.testing.assert_array_equal(again.hist_counts, scan.hist_counts)


def test_feature_scan_memory_does_not_grow_with_the_rows():
    sae = make_sae("topk")
    small, large = (scan_features(batched(*make_rows(frames, seed=2), 16), sae, top_n=4, bins=8)
                    for frames in (20, 400))
    assert large.rows > 10 * small.rows
    for name in ("top_values", "hist_counts", "hist_exponent", "firing", "activation_sum"):
        assert getattr(large, name).nbytes == getattr(small, name).nbytes


def test_frame_contexts_give_every_token_of_the_chosen_frames():
    sae = make_sae()
    rows, columns = make_rows()
    acts = sae.encode(rows).numpy()
    contexts = frame_contexts(batched(rows, columns, 4), sae, {104: [5, 2], 130: [2, 5], 999: [1]})
    assert sorted(contexts) == [104, 130]
    for index, context in contexts.items():
        members = np.flatnonzero(columns["index"] == index)
        np.testing.assert_array_equal(context.token_position, columns["token_position"][members])
        np.testing.assert_array_equal(context.token_id, columns["token_id"][members])
        np.testing.assert_allclose(context.values(2), acts[members, 2])
        np.testing.assert_allclose(context.values(5), acts[members, 5])


def test_feature_scan_refuses_batches_without_columns_or_of_another_width():
    sae = make_sae()
    rows, columns = make_rows(frames=3)
    with pytest.raises(ValueError, match=r"^row batch 0: column `token_id` is missing$"):
        scan_features([(rows, {k: v for k, v in columns.items() if k != "token_id"})], sae)
    with pytest.raises(ValueError, match=r"^row batch 0: rows are \(\d+, 5\), SAE tiny expects \(\*, 8\)$"):
        scan_features([(rows[:, :5], columns)], sae)
    with pytest.raises(ValueError, match="bins is 12, expected a power of two"):
        scan_features([], sae, bins=12)
