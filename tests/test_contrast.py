"""Contrast manifests: known answers on designed motion, the seed's window rule, formats and errors."""

from __future__ import annotations

import json
import math
import re
import shutil

import numpy as np
import pandas as pd
import pytest
from helpers_dataset import (
    CLOSE,
    CONTRAST_AXIS,
    OPEN,
    STOVE,
    contrast_episodes,
    write_contrast_dataset,
)
from pydantic import ValidationError
from reference_formats import FORMATS
from typer.testing import CliRunner

from latent_steering_cli import app
from steering_core.data.contrast import (
    ContrastSettings,
    build_manifest,
    interaction_window,
    read_manifest,
    write_manifest,
)
from steering_core.data.dataset import dataset_fingerprint

REFERENCE = FORMATS / "open_vs_close.json"
SEED_SEGMENT_FIELDS = {"task", "file", "demo", "start_step", "end_step", "axis_delta", "axis_values", "episode_index"}
DATA_FILE = {0: "data/chunk-000/file-000.parquet", 1: "data/chunk-000/file-001.parquet"}


@pytest.fixture(scope="module")
def root(tmp_path_factory):
    return write_contrast_dataset(tmp_path_factory.mktemp("ds") / "contrast")


def designed(task):
    """Return (episode_index, states as float64) of the designed demos of `task`."""
    return [(i, s.astype(np.float64)) for i, (t, s) in enumerate(contrast_episodes()) if t == task]


def hand_stats(values):
    """Return mean and population std of a list of floats, written out."""
    mean = sum(values) / len(values)
    return mean, math.sqrt(sum((v - mean) ** 2 for v in values) / len(values))


def loop_window(series, progress_frac, pad):
    """The window rule as a plain loop (main branch only: the designed demos all make progress)."""
    threshold = max(abs(series[-1] - series[0]) * progress_frac, 1e-6)
    hits = [t for t in range(len(series)) if abs(series[t] - series[0]) >= threshold]
    assert hits, "designed demos always reach the threshold"
    start, end = max(hits[0] - pad, 0), min(hits[-1] + pad, len(series) - 1)
    return (start, end) if end > start else (start, min(start + 1, len(series) - 1))


def expected_segments(task, episodes, progress_frac=0.35, pad=8):
    rows = []
    for episode, states in episodes:
        start, end = loop_window(list(states[:, CONTRAST_AXIS]), progress_frac, pad)
        values = states[start : end + 1, CONTRAST_AXIS]
        rows.append(dict(
            task=task, file=DATA_FILE[episode >= 4], demo=f"episode_{episode:06d}", start_step=start,
            end_step=end, axis_delta=values[-1] - values[0], axis_values=tuple(values), episode_index=episode,
        ))
    return rows


def test_known_answer_manifest(root):
    manifest = build_manifest(root, OPEN, CLOSE)
    open_demos, close_demos = designed(OPEN), designed(CLOSE)
    mean_a, std_a = hand_stats([s[-1, CONTRAST_AXIS] - s[0, CONTRAST_AXIS] for _, s in open_demos])
    mean_b, std_b = hand_stats([s[-1, CONTRAST_AXIS] - s[0, CONTRAST_AXIS] for _, s in close_demos])
    assert manifest.axis.index == CONTRAST_AXIS  # not 0 (same sign) nor 6 (CLOSE below min_abs_delta)
    assert list(manifest.axis.mean_delta_per_task) == [OPEN, CLOSE]
    assert manifest.axis.mean_delta_per_task[OPEN] == pytest.approx(mean_a, rel=1e-12) and mean_a > 0.2
    assert manifest.axis.mean_delta_per_task[CLOSE] == pytest.approx(mean_b, rel=1e-12) and mean_b < -0.16
    effect = (mean_a - mean_b) / math.sqrt((std_a**2 + std_b**2) / 2)
    assert manifest.axis.effect_size == pytest.approx(effect, rel=1e-6) and effect > 0
    expected = expected_segments(OPEN, open_demos) + expected_segments(CLOSE, close_demos)
    assert [seg.model_dump() for seg in manifest.segments] == expected  # bit-identical float64 values
    assert manifest.dataset.fingerprint == dataset_fingerprint(root)
    assert manifest.dataset.repo_id == "contrast" and manifest.dataset.root == str(root)
    assert manifest.dataset.settings == ContrastSettings()

    swapped = build_manifest(root, CLOSE, OPEN)
    assert swapped.axis.index == CONTRAST_AXIS
    assert swapped.axis.effect_size == pytest.approx(-manifest.axis.effect_size)
    assert [s.task for s in swapped.segments] == [CLOSE] * 3 + [OPEN] * 3


def test_settings_select_demos_and_shape_windows(root):
    two = build_manifest(root, OPEN, CLOSE, ContrastSettings(max_demos_per_task=2))
    assert [s.episode_index for s in two.segments] == [0, 3, 1, 4]
    mean_a, _ = hand_stats([s[-1, CONTRAST_AXIS] - s[0, CONTRAST_AXIS] for _, s in designed(OPEN)[:2]])
    assert two.axis.mean_delta_per_task[OPEN] == pytest.approx(mean_a, rel=1e-12)

    explicit = build_manifest(root, OPEN, CLOSE, ContrastSettings(task_a_episodes=(5, 3, 5), task_b_episodes=(6,)))
    assert [s.episode_index for s in explicit.segments] == [3, 5, 6]
    assert math.isfinite(explicit.axis.effect_size)  # one CLOSE demo: std 0

    tight = build_manifest(root, OPEN, CLOSE, ContrastSettings(progress_frac=1.0, pad=0))
    demos = designed(OPEN) + designed(CLOSE)
    expected = expected_segments(OPEN, designed(OPEN), 1.0, 0) + expected_segments(CLOSE, designed(CLOSE), 1.0, 0)
    assert [(s.start_step, s.end_step) for s in tight.segments] == [(r["start_step"], r["end_step"]) for r in expected]
    assert all(s.end_step == len(states) - 1 for s, (_, states) in zip(tight.segments, demos, strict=True))


def test_segments_per_class_keeps_the_furthest_progress(root):
    full = build_manifest(root, OPEN, CLOSE)
    kept = build_manifest(root, OPEN, CLOSE, ContrastSettings(segments_per_class=2))
    assert kept.axis == full.axis  # the axis still comes from every demo
    for task, direction in ((OPEN, 1), (CLOSE, -1)):
        candidates = [s for s in full.segments if s.task == task]
        best = sorted(candidates, key=lambda s: direction * s.axis_delta, reverse=True)[:2]
        assert [s for s in kept.segments if s.task == task] == sorted(best, key=lambda s: s.episode_index)
    assert build_manifest(root, OPEN, CLOSE, ContrastSettings(segments_per_class=9)).segments == full.segments


@pytest.mark.parametrize(
    ("series", "progress_frac", "pad", "window"),
    [
        ([0, 0, 0, 1, 2, 3, 4, 4, 4, 4], 0.35, 2, (2, 9)),         # |disp| >= 1.4 from frame 4 on
        ([0, 0, 0, -1, -2, -3, -4, -4, -4, -4], 0.35, 0, (4, 9)),  # the direction does not matter
        ([0, 5, 5, 1], 0.35, 0, (1, 3)),                           # overshoot, then settles at +1
        ([0, 5, 5, 1], 1.0, 10, (0, 3)),                           # padding is clipped to the demo
        ([0.3] * 12, 0.35, 8, (0, 11)),                            # no motion at all: the whole demo
        ([0.3], 0.35, 8, (0, 0)),                                  # a one-frame demo
        (np.cumsum(np.arange(60) * 1e-10), 0.35, 8, (46, 59)),     # no progress: the 6 largest steps 54..59
        (np.cumsum(np.r_[0, np.arange(59, 0, -1)] * 1e-10), 0.35, 2, (0, 8)),  # largest steps 1..6
        (np.r_[np.zeros(6), 1e-7, 0, 0], 0.35, 0, (4, 8)),        # 5 largest steps: 6, 7, then ties 4, 5, 8
    ],
)
def test_interaction_window_known_answers(series, progress_frac, pad, window):
    assert interaction_window(np.asarray(series, dtype=np.float64), progress_frac, pad) == window


def test_reference_manifest_loads_unchanged(tmp_path):
    original = json.loads(REFERENCE.read_text())
    manifest = read_manifest(REFERENCE)
    assert manifest.dataset is None and len(manifest.segments) == 100
    assert manifest.to_json() == original
    assert set(manifest.to_json()) == {"axis", "segments"}
    write_manifest(manifest, tmp_path / "again.json")
    assert json.loads((tmp_path / "again.json").read_text()) == original


def test_written_manifest_keeps_the_seed_fields(root, tmp_path):
    manifest = build_manifest(root, OPEN, CLOSE, ContrastSettings(pad=3, task_b_episodes=(1, 6)))
    path = write_manifest(manifest, tmp_path / "m" / "open_vs_close.json")
    payload = json.loads(path.read_text())
    assert set(payload) == {"axis", "segments", "dataset"}
    assert set(payload["axis"]) == {"index", "effect_size", "mean_delta_per_task"}
    assert all(set(seg) == SEED_SEGMENT_FIELDS for seg in payload["segments"])
    assert payload["dataset"]["settings"]["task_b_episodes"] == [1, 6]
    assert read_manifest(path) == manifest
    assert [p.name for p in path.parent.iterdir()] == ["open_vs_close.json"]  # no temp file left behind


def test_task_errors(root, tmp_path):
    with pytest.raises(ValueError, match=rf"task 'open the drawer' is not in the dataset \(3 tasks\); "
                                         rf"closest task texts: \['{OPEN}'"):
        build_manifest(root, "open the drawer", CLOSE)
    with pytest.raises(ValueError, match=f"task A and task B are both '{OPEN}'; a contrast needs two different tasks"):
        build_manifest(root, OPEN, OPEN.upper())

    lonely = shutil.copytree(root, tmp_path / "lonely")
    tasks = pd.read_parquet(lonely / "meta/tasks.parquet")
    pd.concat([tasks, pd.DataFrame({"task_index": [3]}, index=["turn off the stove"])]).to_parquet(
        lonely / "meta/tasks.parquet"
    )
    with pytest.raises(ValueError, match="task 'turn off the stove' has no episodes"):
        build_manifest(lonely, OPEN, "turn off the stove")


def test_episode_list_errors(root):
    with pytest.raises(ValueError) as err:
        build_manifest(root, OPEN, CLOSE, ContrastSettings(task_a_episodes=(0, 1, 42)))
    assert str(err.value) == (
        f"--task-a-episodes: episode(s) {{1: '{CLOSE}', 42: 'not in the dataset'}} are not episodes of '{OPEN}'; "
        "its episodes are [0, 3, 5]"
    )
    with pytest.raises(ValueError, match=f"--task-b-episodes: the episode list for '{CLOSE}' is empty"):
        build_manifest(root, OPEN, CLOSE, ContrastSettings(task_b_episodes=()))


def test_no_opposite_axis_names_the_closest(root):
    with pytest.raises(ValueError) as err:
        build_manifest(root, OPEN, STOVE)
    message = str(err.value)
    assert message.startswith(
        f"no state axis moves in opposite directions for '{OPEN}' and '{STOVE}' with |mean terminal displacement| "
        ">= min_abs_delta 0.05 in both; closest: axis "
    )
    assert message.endswith("Lower --min-abs-delta or choose two tasks with opposite motion.")
    open_mean = np.mean([s[-1, 0] - s[0, 0] for _, s in designed(OPEN)])
    stove_mean = np.mean([s[-1, 0] - s[0, 0] for _, s in designed(STOVE)])
    assert f"axis 0 (mean '{OPEN}' {open_mean:+.4f}, '{STOVE}' {stove_mean:+.4f}: same sign)" in message
    assert message.count("axis ") == 1 + 3
    with pytest.raises(ValueError, match="opposite signs but below min_abs_delta"):
        build_manifest(root, OPEN, CLOSE, ContrastSettings(min_abs_delta=0.5))


def test_settings_are_validated():
    with pytest.raises(ValidationError, match="progress_frac"):
        ContrastSettings(progress_frac=0)
    with pytest.raises(ValidationError, match="pad"):
        ContrastSettings(pad=-1)
    with pytest.raises(ValidationError, match="Extra inputs are not permitted"):
        ContrastSettings(padding=3)
    assert ContrastSettings().fingerprint() == ContrastSettings(pad=8).fingerprint()
    assert ContrastSettings().fingerprint() != ContrastSettings(pad=9).fingerprint()


def test_invalid_manifest_files(tmp_path):
    payload = json.loads(REFERENCE.read_text())
    payload["segments"][0]["axis_values"] = payload["segments"][0]["axis_values"][:-1]
    payload["segments"][1]["task"] = "turn on the stove"
    payload["segments"][2]["start_step"] = 80
    path = tmp_path / "bad.json"
    path.write_text(json.dumps(payload))
    with pytest.raises(ValueError) as err:
        read_manifest(path)
    message = str(err.value)
    assert message.startswith(f"{path}: not a valid contrast manifest")
    assert "segments[0] (episode_000050): axis_values has 54 values, expected end_step - start_step + 1 = 55" in message
    assert "segments[1] (episode_000051): task 'turn on the stove' is not in axis.mean_delta_per_task" in message
    assert "segments[2] (episode_000052): start_step 80, end_step 68; expected 0 <= start <= end" in message
    payload = json.loads(REFERENCE.read_text())
    payload["axis"]["note"] = "x"
    path.write_text(json.dumps(payload))
    with pytest.raises(ValueError, match="axis.note"):
        read_manifest(path)
    with pytest.raises(FileNotFoundError, match="missing.json: file not found"):
        read_manifest(tmp_path / "missing.json")


def test_cli_manifest(root, tmp_path):
    output = tmp_path / "manifests" / "open_vs_close.json"
    result = CliRunner().invoke(app, [
        "manifest", "--lerobot-root", str(root), "--task-a-text", OPEN, "--task-b-text", CLOSE,
        "--output", str(output), "--task-a-episodes", "0,3", "--task-a-episodes", "5", "--pad", "4",
        "--segments-per-class", "2", "--repo-id", "lab/contrast",
    ])
    assert result.exit_code == 0, result.output
    settings = ContrastSettings(pad=4, task_a_episodes=(0, 3, 5), segments_per_class=2)
    assert read_manifest(output) == build_manifest(root, OPEN, CLOSE, settings, repo_id="lab/contrast")
    manifest = read_manifest(output)
    assert f"axis {CONTRAST_AXIS}, effect size {manifest.axis.effect_size:.3f}" in result.output
    assert f"'{OPEN}': 2 segment(s)" in result.output and f"'{CLOSE}': 2 segment(s)" in result.output


def test_cli_manifest_errors(root, tmp_path):
    output = tmp_path / "m.json"
    base = ["manifest", "--lerobot-root", str(root), "--task-b-text", CLOSE, "--output", str(output)]
    result = CliRunner().invoke(app, [*base, "--task-a-text", "open the drawer"])
    assert result.exit_code == 1
    assert "error: " in result.output and "is not in the dataset" in result.output
    result = CliRunner().invoke(app, [*base, "--task-a-text", OPEN, "--task-a-episodes", "0-3"])
    assert result.exit_code == 1
    assert f"episode(s) {{1: '{CLOSE}', 2: '{STOVE}'}} are not episodes of '{OPEN}'" in result.output
    result = CliRunner().invoke(app, [*base, "--task-a-text", OPEN, "--task-a-episodes", "3-x"])
    flat = " ".join(re.sub(r"[│╭╮╰╯─]", " ", result.output).split())  # typer draws a box around usage errors
    assert result.exit_code == 2 and "'3-x' is not an episode index or range like 3-7" in flat
    assert not output.exists()
