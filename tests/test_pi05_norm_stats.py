"""norm_stats.json reading, quantile normalisation and state bins against hand-computed values."""

from __future__ import annotations

import json

import numpy as np
import pytest

from steering_core.pi05.norm_stats import (
    discretize_state,
    norm_stats_path,
    quantile_normalize,
    quantile_unnormalize,
    read_norm_stats,
)
from steering_core.synthetic.pi05 import random_norm_stats, tiny_arch, write_pi05_checkpoint


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory):
    return write_pi05_checkpoint(tmp_path_factory.mktemp("pi05") / "ckpt", tiny_arch(), seed=5)


def write_stats(path, payload):
    path.write_text(json.dumps(payload))
    return path


def test_reads_checkpoint_assets_and_plain_files(checkpoint, tmp_path):
    expected = random_norm_stats(5)["norm_stats"]
    stats = read_norm_stats(checkpoint)
    assert sorted(stats) == ["actions", "state"]
    assert stats["state"].q01.tolist() == expected["state"]["q01"]
    assert stats["actions"].std.tolist() == expected["actions"]["std"]
    libero = checkpoint / "assets/physical-intelligence/libero/norm_stats.json"
    assert norm_stats_path(checkpoint / "model.safetensors") == libero
    plain = write_stats(tmp_path / "stats.json", {"norm_stats": {"state": {"mean": [1.0], "std": [2.0]}}})
    only_moments = read_norm_stats(plain)["state"]
    assert only_moments.mean.tolist() == [1.0] and only_moments.q01 is None


def test_missing_stats_name_the_asset_ids_present(checkpoint):
    with pytest.raises(FileNotFoundError) as err:
        read_norm_stats(checkpoint, asset_id="physical-intelligence/droid")
    message = str(err.value)
    assert message.startswith(f"{checkpoint}/assets/physical-intelligence/droid/norm_stats.json: norm stats not found")
    assert "asset ids with norm stats in" in message and ": physical-intelligence/libero)" in message


def test_malformed_stats_list_every_problem(tmp_path):
    bad = write_stats(
        tmp_path / "bad.json",
        {"norm_stats": {"state": {"mean": [0.0, 1.0], "std": "wide", "q01": [0.0], "q99": [1.0, 2.0]}, "actions": 3}},
    )
    with pytest.raises(ValueError) as err:
        read_norm_stats(bad)
    message = str(err.value)
    assert message.startswith(f"{bad}: ")
    assert "`state.std` is 'wide', expected a list of finite numbers" in message
    assert "`state` fields have different lengths {'mean': 2, 'q01': 1, 'q99': 2}" in message
    assert "`actions` is int, expected an object with mean, std, q01, q99" in message
    with pytest.raises(ValueError, match="expected an object with a `norm_stats` mapping, found list"):
        read_norm_stats(write_stats(tmp_path / "list.json", [1, 2]))


def test_quantile_normalize_by_hand(tmp_path):
    stats = read_norm_stats(
        write_stats(tmp_path / "s.json", {"norm_stats": {"state": {
            "mean": [0, 0, 0], "std": [1, 1, 1], "q01": [0.0, -1.0, 5.0], "q99": [2.0, 1.0, 6.0]}}})
    )["state"]
    # (x - q01) / (q99 - q01 + 1e-6) * 2 - 1, stats truncated to the state's 2 dims, no clipping
    out = quantile_normalize(np.array([1.0, 3.0], dtype=np.float32), stats)
    assert out.dtype == np.float64
    assert out.tolist() == pytest.approx([1.0 / 2.000001 * 2 - 1, 4.0 / 2.000001 * 2 - 1], rel=1e-12)
    with pytest.raises(ValueError, match="state has 4 dimensions but the norm stats only 3"):
        quantile_normalize(np.zeros(4), stats)
    no_quantiles = read_norm_stats(
        write_stats(tmp_path / "m.json", {"norm_stats": {"state": {"mean": [0], "std": [1]}}})
    )["state"]
    with pytest.raises(ValueError, match="norm stats have no q01/q99"):
        quantile_normalize(np.zeros(1), no_quantiles)


def test_quantile_unnormalize_by_hand(tmp_path):
    stats = read_norm_stats(
        write_stats(tmp_path / "a.json", {"norm_stats": {"actions": {
            "mean": [0, 0], "std": [1, 1], "q01": [0.0, -1.0], "q99": [2.0, 1.0]}}})
    )["actions"]
    # (x + 1) / 2 * (q99 - q01 + 1e-6) + q01 on the stats' 2 leading dims; the third passes through
    out = quantile_unnormalize(np.array([[0.5, -1.0, 7.0]], dtype=np.float32), stats)
    assert out.dtype == np.float64 and out.shape == (1, 3)
    assert out[0].tolist() == pytest.approx([0.75 * 2.000001, -1.0, 7.0], rel=1e-12)
    # the inverse of quantile_normalize on the leading dims
    values = np.array([0.3, -0.2])
    assert quantile_unnormalize(quantile_normalize(values, stats), stats) == pytest.approx(values, abs=1e-12)
    with pytest.raises(ValueError, match="values have 1 dimensions but the norm stats 2; expected at most 1"):
        quantile_unnormalize(np.zeros(1), stats)


def test_discretize_state_by_hand():
    values = np.array([-1.5, -1.0, -0.9921875, -0.5, 0.0, 0.5, 0.99, 0.9921874, 0.9921875, 2.0])
    # floor((x + 1) * 128) inside [-1, 0.9921875); -1 below; 255 from 0.9921875 up
    assert discretize_state(values).tolist() == [-1, 0, 1, 64, 128, 192, 254, 254, 255, 255]
    assert discretize_state(values).dtype == np.int64
