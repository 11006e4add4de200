"""The feature browser: the streaming feature scan, the static HTML page (in headless Chromium) and the Neuronpedia export."""

from __future__ import annotations

import asyncio
import base64
import html
import itertools
import json
import re
import shutil
import subprocess
import time
import urllib.request
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
from safetensors.torch import load_file
from torchvision.io import decode_png

from steering_core.capture.shards import ROW_COLUMNS, open_shard, read_run_metadata
from steering_core.layout import layer_dir
from steering_core.sae.formats import SaeConfig
from steering_core.sae.model import StandardSae, TopKSae, load_sae
from steering_core.sae_quality.feature_page import read_pair_latents, sentencepiece_text, write_feature_page
from steering_core.sae_quality.feature_scan import FeatureScan, frame_contexts, read_feature_scan, scan_features
from steering_core.sae_quality.neuronpedia import read_jsonl_gz, write_neuronpedia
from steering_core.storage.fileio import read_json

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


# ----------------------------------------------------------------------------- on the finished demo run

LAYER = 1
REPO = "libero_demo_lerobot"
CHROMIUM = shutil.which("chromium")
SHOWN = 4  # examples per latent on the page


@dataclass(frozen=True)
class DemoPage:
    world: Any
    scan: FeatureScan
    sae: Any
    path: Path
    html: str
    pieces: Any  # token id -> SentencePiece piece


@pytest.fixture(scope="module")
def demo_page(attack_world, tmp_path_factory) -> DemoPage:
    """The feature page of the demo run's layer 1, through the SAE trained on its rows and its steering pairs."""
    import sentencepiece

    run = attack_world.data / "residuals" / "demo"
    sae = load_sae(attack_world.data / "saes" / "demo" / layer_dir(LAYER) / "sae")  # what the CLI steps steered with
    scan = scan_features(shard_batches(run, LAYER), sae, top_n=6)
    pieces = sentencepiece.SentencePieceProcessor(model_file=str(attack_world.tokenizer)).id_to_piece
    path = write_feature_page(
        tmp_path_factory.mktemp("page") / "features.html", scan, sae, lambda episodes: shard_batches(run, LAYER, episodes),
        steering_layer=attack_world.data / "latent_steering" / "layer01", dataset_root=attack_world.dataset,
        repo_id=REPO, token_text=sentencepiece_text(attack_world.tokenizer), pair_top_k=3, most_active=3, examples=SHOWN)
    return DemoPage(attack_world, scan, sae, path, path.read_text(encoding="utf-8"), pieces)


def read_json_lines(path: Path) -> list[dict]:
    return [json.loads(line) for line in path.read_text(encoding="utf-8").splitlines()]


def section(page: str, latent: int) -> str:
    start = page.index(f'<section id="latent-{latent}">')
    return page[start : page.index("</section>", start)]


def frame_rows(world, index: int | None) -> tuple[torch.Tensor, dict[str, np.ndarray]]:
    """Every row of one frame (None: of the run), read straight from the run's shards."""
    rows, columns = zip(*shard_batches(world.data / "residuals" / "demo", LAYER, size=10**6), strict=True)
    rows, columns = torch.cat(rows), {k: np.concatenate([c[k] for c in columns]) for k in ROW_COLUMNS}
    keep = columns["index"] == index if index is not None else np.ones(len(rows), dtype=bool)
    return rows[torch.from_numpy(keep)], {k: v[keep] for k, v in columns.items()}


def dataset_frame(world, index: int, size: int) -> np.ndarray:
    """The agentview image of a dataset index, decoded from the dataset's parquet with PIL: (size, size, 3) uint8."""
    import io

    import pyarrow.parquet as pq
    from PIL import Image

    for file in sorted((world.dataset / "data").rglob("*.parquet")):
        table = pq.read_table(file, columns=["index", "image"]).to_pydict()
        if index in table["index"]:
            image = Image.open(io.BytesIO(table["image"][table["index"].index(index)]["bytes"])).convert("RGB")
            return np.asarray(image.resize((size, size), Image.BILINEAR))
    raise AssertionError(f"index {index} not in the dataset")


def data_uri_pixels(uri: str) -> np.ndarray:
    from torchvision.io import decode_image

    data = base64.b64decode(uri.split(",", 1)[1])
    return decode_image(torch.frombuffer(bytearray(data), dtype=torch.uint8)).permute(1, 2, 0).numpy()


def test_feature_page_shows_each_pairs_top_latents_with_their_frames_tokens_and_decoder_cosines(demo_page):
    page, world, sae = demo_page.html, demo_page.world, demo_page.sae
    assert all(url.startswith(("data:", "#")) for url in re.findall(r'(?:src|href)="([^"]*)"', page))
    assert "http" not in page and "<script" not in page
    steering = world.data / "latent_steering" / "layer01"
    pairs = read_json(steering / "pairwise_stats.json")["pairs"]
    for pair in pairs:
        latent_direction = load_file(steering / pair / "latent_direction.safetensors")["latent_direction"]
        residual = load_file(steering / pair / "residual_direction.safetensors")["residual_direction"].double()
        top = [int(i) for i in np.argsort(-np.abs(latent_direction.numpy()), kind="stable")[:3]]
        for rank, latent in enumerate(top):
            text = section(page, latent)
            decoder_row = sae.W_dec[latent].double()
            cosine = float(decoder_row @ residual / (decoder_row.norm() * residual.norm()))
            assert (f'<tr class="member"><td>{pair}</td><td>{rank + 1} ({float(latent_direction[latent]):+.3g})</td>'
                    f"<td>{cosine:+.3f}</td></tr>") in text
    latent = int(np.argsort(-np.abs(load_file(steering / pairs[0] / "latent_direction.safetensors")[
        "latent_direction"].numpy()), kind="stable")[0])
    text = section(page, latent)
    examples = demo_page.scan.examples(latent)[:SHOWN]
    thumbnails = re.findall(r'<img src="(data:image/jpeg;base64,[^"]+)"', text)
    assert len(thumbnails) == len(examples) == SHOWN
    for example, thumbnail in zip(examples, thumbnails, strict=True):
        rows, columns = frame_rows(world, example["index"])
        acts = sae.encode(rows)[:, latent].numpy()
        peak = int(np.argmax(acts))
        assert example["value"] == pytest.approx(float(acts[peak]), rel=1e-6)
        assert f'{example["value"]:.4g}</b> · episode {int(columns["episode_index"][0])} · frame ' \
               f'{int(columns["frame_index"][0])} · index {example["index"]}' in text
        peak_text = demo_page.pieces(int(columns["token_id"][peak])).replace("\u2581", " ")
        assert re.search(rf'<mark class="peak" [^>]*>{re.escape(html.escape(peak_text))}</mark>', text)
        shown, expected = data_uri_pixels(thumbnail).astype(float), dataset_frame(world, example["index"], 112)
        assert shown.shape == expected.shape and np.abs(shown - expected).mean() < 8
    edges, counts = demo_page.scan.histogram(latent)
    assert counts.sum() == demo_page.scan.firing[latent] and text.count("<rect") == np.count_nonzero(counts)


def test_pairs_steered_through_another_sae_keep_their_residual_direction_but_list_no_latents(demo_page):
    steering = demo_page.world.data / "latent_steering" / "layer01"
    own = read_pair_latents(steering, 3, demo_page.sae)
    other = read_pair_latents(steering, 3, load_sae(demo_page.world.sae(2)))  # same widths, other weights
    assert [len(pair.latents) for pair in own] == [3] * len(own) and len(own) == 2
    assert [pair.latents for pair in other] == [(), ()]
    for a, b in zip(own, other, strict=True):
        assert a.pair == b.pair and torch.equal(a.residual_direction, b.residual_direction)


@pytest.mark.skipif(CHROMIUM is None, reason="Debian's chromium is not installed (apt-get install -y chromium)")
def test_feature_page_loads_in_headless_chromium_without_console_errors_and_shows_the_thumbnails(demo_page, tmp_path):
    broken = tmp_path / "broken.html"  # proves the listener hears what it must refuse
    broken.write_text('<!DOCTYPE html><img src="missing.png"><script>console.error("boom")</script>')
    (page_problems, images, shot), (broken_problems, _, _) = chromium_load([demo_page.path, broken], tmp_path)
    assert page_problems == []
    assert any("boom" in problem for problem in broken_problems)
    assert any("missing.png" in problem or "ERR_FILE_NOT_FOUND" in problem for problem in broken_problems)
    assert len(images) == demo_page.html.count("<img ") and all(images) and images[0] == [True, 112, 112]
    first = data_uri_pixels(re.search(r'<img src="(data:image/jpeg;base64,[^"]+)"', demo_page.html)[1])
    screen = decode_png(torch.frombuffer(bytearray(shot), dtype=torch.uint8))[:3].permute(1, 2, 0).numpy()
    rms, where = best_match(screen.mean(axis=2), first.mean(axis=2))
    assert first.mean(axis=2).std() > 10 and rms < 6, (rms, where)  # the thumbnail is on screen, pixel for pixel


def best_match(screen: np.ndarray, template: np.ndarray) -> tuple[float, tuple[int, int]]:
    """Return the smallest RMS difference of `template` against any window of `screen` (FFT correlation), and where."""
    screen, template = screen.astype(np.float64), template.astype(np.float64)
    (height, width), (h, w) = screen.shape, template.shape
    shape = (height, width)
    correlation = np.fft.irfft2(np.fft.rfft2(screen) * np.conj(np.fft.rfft2(template, shape)), shape)
    squares = np.pad(np.square(screen), ((1, 0), (1, 0))).cumsum(0).cumsum(1)
    window = squares[h:, w:] - squares[:-h, w:] - squares[h:, :-w] + squares[:-h, :-w]  # (H-h+1, W-w+1)
    ssd = window - 2 * correlation[: height - h + 1, : width - w + 1] + np.square(template).sum()
    y, x = np.unravel_index(np.argmin(ssd), ssd.shape)
    return float(np.sqrt(max(ssd[y, x], 0) / template.size)), (int(y), int(x))


def chromium_load(pages: list[Path], tmp_path: Path) -> list[tuple[list[str], list, bytes]]:
    """Open each page from disk in one headless Chromium through the DevTools protocol.

    Returns per page: the console errors and warnings, exceptions and failed loads; [complete, width, height]
    of every <img>; a PNG screenshot of the 1200x1000 viewport.
    """
    profile = tmp_path / "chromium-profile"
    profile.mkdir()
    browser = subprocess.Popen(
        [CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
         "--disable-background-networking", "--disable-component-update", "--disable-sync",
         f"--user-data-dir={profile}", "--remote-debugging-port=0", "--window-size=1200,1000", "about:blank"],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        port_file, deadline = profile / "DevToolsActivePort", time.monotonic() + 60
        while not (port_file.is_file() and port_file.read_text().strip()):
            assert time.monotonic() < deadline and browser.poll() is None, "chromium did not start"
            time.sleep(0.05)
        port = int(port_file.read_text().split()[0])
        opener = urllib.request.build_opener(urllib.request.ProxyHandler({}))
        targets = json.loads(opener.open(f"http://127.0.0.1:{port}/json/list", timeout=30).read())
        socket_url = next(t["webSocketDebuggerUrl"] for t in targets if t["type"] == "page")
        return asyncio.run(asyncio.wait_for(_drive(socket_url, [page.as_uri() for page in pages]), 120))
    finally:
        browser.terminate()
        browser.wait(30)


async def _drive(socket_url: str, urls: list[str]) -> list[tuple[list[str], list, bytes]]:
    import websockets

    async with websockets.connect(socket_url, max_size=None) as socket:
        numbers, problems, loaded = itertools.count(1), [], []

        def note(message: dict) -> None:
            method, params = message.get("method"), message.get("params", {})
            if method == "Runtime.consoleAPICalled" and params["type"] in ("error", "warning", "assert"):
                problems.append(" ".join(str(arg.get("value", arg.get("description"))) for arg in params["args"]))
            elif method == "Runtime.exceptionThrown":
                problems.append(json.dumps(params["exceptionDetails"]))
            elif method == "Log.entryAdded" and params["entry"]["level"] in ("error", "warning"):
                problems.append(f'{params["entry"]["text"]} {params["entry"].get("url", "")}')
            elif method == "Page.loadEventFired":
                loaded.append(True)

        async def call(method: str, **params) -> dict:
            number = next(numbers)
            await socket.send(json.dumps({"id": number, "method": method, "params": params}))
            while True:
                message = json.loads(await socket.recv())
                if message.get("id") == number:
                    assert "error" not in message, message
                    return message["result"]
                note(message)

        for domain in ("Page", "Runtime", "Log"):
            await call(f"{domain}.enable")
        results = []
        for url in urls:
            problems.clear()
            loaded.clear()
            await call("Page.navigate", url=url)
            while not loaded:
                note(json.loads(await socket.recv()))
            images = await call("Runtime.evaluate", returnByValue=True, expression=(
                "[...document.images].map(i => [i.complete, i.naturalWidth, i.naturalHeight])"))
            shot = await call("Page.captureScreenshot", format="png")
            results.append((list(problems), images["result"]["value"], base64.b64decode(shot["data"])))
        return results


# the record fields of Neuronpedia's exporter (neuronpedia_utils/db_models/feature.py and activation.py)
NEURONPEDIA_FEATURE_FIELDS = {
    "modelId", "layer", "index", "creatorId", "createdAt", "maxActApprox", "hasVector", "vector", "vectorLabel",
    "vectorDefaultSteerStrength", "hookName", "topkCosSimIndices", "topkCosSimValues", "neuron_alignment_indices",
    "neuron_alignment_values", "neuron_alignment_l1", "correlated_neurons_indices", "correlated_neurons_pearson",
    "correlated_neurons_l1", "correlated_features_indices", "correlated_features_pearson", "correlated_features_l1",
    "neg_str", "neg_values", "pos_str", "pos_values", "frac_nonzero", "freq_hist_data_bar_heights",
    "freq_hist_data_bar_values", "logits_hist_data_bar_heights", "logits_hist_data_bar_values", "decoder_weights_dist",
}
NEURONPEDIA_ACTIVATION_FIELDS = {
    "id", "tokens", "index", "layer", "modelId", "maxValue", "maxValueTokenIndex", "minValue", "values", "creatorId",
    "dataSource", "dataIndex", "dfaValues", "dfaTargetIndex", "dfaMaxValue", "createdAt", "lossValues",
    "logitContributions", "binMin", "binMax", "binContains", "qualifyingTokenIndex",
}


def test_neuronpedia_export_has_its_batch_layout_and_every_tokens_activation(demo_page, tmp_path):
    world, sae, scan = demo_page.world, demo_page.sae, demo_page.scan
    run = world.data / "residuals" / "demo"

    def export(out: Path) -> Path:
        return write_neuronpedia(out, scan, sae, lambda episodes: shard_batches(run, LAYER, episodes), layer=LAYER,
                                 token_text=demo_page.pieces, examples=3, features_per_batch=100,
                                 created_at="2026-12-01T00:00:00+00:00", dataset=REPO)

    source = export(tmp_path / "a")
    assert source == tmp_path / "a" / "pi05" / "1-res-pi05"
    files = sorted(str(path.relative_to(source)) for path in source.rglob("*") if path.is_file())
    rows, columns = frame_rows(world, None)
    acts = sae.encode(rows).numpy()
    fired = int((acts > 0).any(axis=0).sum())
    batches = -(-fired // 100)
    assert files == sorted([*(f"{kind}/batch-{n}.jsonl.gz" for kind in ("activations", "features")
                              for n in range(batches)), "model.jsonl", "source.jsonl", "sourceset.jsonl"])
    features = [r for n in range(batches) for r in read_jsonl_gz(source / "features" / f"batch-{n}.jsonl.gz")]
    activations = [r for n in range(batches) for r in read_jsonl_gz(source / "activations" / f"batch-{n}.jsonl.gz")]
    assert len(features) == fired and all(set(f) == NEURONPEDIA_FEATURE_FIELDS for f in features)
    assert all(set(a) == NEURONPEDIA_ACTIVATION_FIELDS for a in activations)
    for feature in features:
        latent = int(feature["index"])
        assert feature["frac_nonzero"] == pytest.approx((acts[:, latent] > 0).mean())
        assert sum(feature["freq_hist_data_bar_heights"]) == (acts[:, latent] > 0).sum()
        mine = [a for a in activations if a["index"] == feature["index"]]
        assert [a["id"] for a in mine] == [f"1-res-pi05-{latent}-{rank}" for rank in range(len(mine))]
        assert 1 <= len(mine) <= 3 and feature["maxActApprox"] == pytest.approx(acts[:, latent].max(), rel=1e-6)
    for record in activations[:20]:
        keep = columns["index"] == int(record["dataIndex"])
        values = acts[keep, int(record["index"])]
        np.testing.assert_allclose(record["values"], values, rtol=1e-6, atol=1e-7)
        assert record["maxValueTokenIndex"] == int(np.argmax(values))
        assert record["tokens"] == [demo_page.pieces(int(t)).replace("\u2581", " ") for t in columns["token_id"][keep]]
    assert read_json_lines(source / "source.jsonl")[0]["num_prompts"] == scan.frames
    again = export(tmp_path / "b")
    assert all((source / name).read_bytes() == (again / name).read_bytes() for name in files)
