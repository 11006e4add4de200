"""Concept maps against a brute-force walk through LeRobotDataset, the seed format, and every bad input."""

from __future__ import annotations

import json
import logging
import shutil
from pathlib import Path

import numpy as np
import pyarrow.compute as pc
import pyarrow.parquet as pq
import pytest
from helpers_dataset import CLOSE, OPEN, brute_force_rows, write_contrast_dataset
from reference_formats import FORMATS
from typer.testing import CliRunner

from latent_steering_cli import app
from steering_core.data.concept_map import build_concept_map, read_concept_map, read_rename_map, write_concept_map
from steering_core.data.contrast import ContrastSettings, build_manifest, write_manifest
from steering_core.data.dataset import read_meta

REFERENCE = FORMATS / "open_vs_close_concept_map.json"
REFERENCE_MANIFEST = FORMATS / "open_vs_close.json"
ROW_FIELDS = ["segment_id", "episode_index", "frame_start", "frame_end", "observed_frame_start",
              "observed_frame_end", "start_index", "end_index", "length"]


@pytest.fixture(scope="module")
def root(tmp_path_factory):
    return write_contrast_dataset(tmp_path_factory.mktemp("ds") / "contrast")


@pytest.fixture(scope="module")
def rows(root):
    return brute_force_rows(root)


@pytest.fixture(scope="module")
def manifest_path(root, tmp_path_factory):
    manifest = build_manifest(root, OPEN, CLOSE, ContrastSettings(pad=2))
    return write_manifest(manifest, tmp_path_factory.mktemp("m") / "open_vs_close.json")


def edit_manifest(source: Path, target: Path, edit) -> Path:
    """Write a copy of a manifest after `edit(payload)`."""
    payload = json.loads(source.read_text())
    edit(payload)
    target.write_text(json.dumps(payload))
    return target


def brute_force_map(manifest_path: Path, rows: dict[str, np.ndarray], rename: dict[str, str]) -> dict:
    """Concepts by walking every dataset row for every segment, then ordering as the seed did."""
    segments = json.loads(manifest_path.read_text())["segments"]
    found = []
    for segment_id, seg in enumerate(segments):
        hits = [
            (int(rows["index"][r]), int(rows["frame_index"][r]))
            for r in range(len(rows["index"]))
            if rows["episode_index"][r] == seg["episode_index"]
            and seg["start_step"] <= rows["frame_index"][r] <= seg["end_step"]
        ]
        indices, frames = zip(*sorted(hits), strict=True)
        found.append((rename.get(seg["task"], seg["task"]), dict(
            segment_id=segment_id, episode_index=seg["episode_index"], frame_start=seg["start_step"],
            frame_end=seg["end_step"], observed_frame_start=min(frames), observed_frame_end=max(frames),
            start_index=min(indices), end_index=max(indices), length=len(indices),
        )))
    concepts: dict[str, list] = {}
    for concept, row in sorted(found, key=lambda item: item[1]["start_index"]):
        concepts.setdefault(concept, []).append(row)
    return concepts


def test_matches_brute_force(root, rows, manifest_path):
    result = build_concept_map(manifest_path, root)
    assert result.sample_count == len(rows["index"]) == 192
    assert result.manifest == str(manifest_path) and result.lerobot_root == str(root) and result.repo_id == "contrast"
    dumped = result.model_dump(mode="json")
    assert dumped["concepts"] == brute_force_map(manifest_path, rows, {})
    # the first dataset episode shows OPEN, so OPEN comes first; segments in dataset order
    assert list(dumped["concepts"]) == list(dumped["concept_count"]) == [OPEN, CLOSE]
    assert dumped["concept_count"] == {OPEN: 3, CLOSE: 3}
    assert [r["episode_index"] for r in dumped["concepts"][CLOSE]] == [1, 4, 6]  # 4 and 6 live in file-001


def test_order_follows_the_dataset_not_the_manifest(root, rows, manifest_path, tmp_path):
    # CLOSE first in the manifest, shuffled, one segment shortened: the map is still in dataset order.
    def shuffle(payload):
        segments = payload["segments"]
        extra = dict(segments[0], start_step=5, end_step=9, axis_values=segments[0]["axis_values"][:5])
        payload["segments"] = [segments[5], segments[3], extra, segments[4], segments[0]]

    path = edit_manifest(manifest_path, tmp_path / "shuffled.json", shuffle)
    result = build_concept_map(path, root, repo_id="lab/other")
    assert result.model_dump(mode="json")["concepts"] == brute_force_map(path, rows, {})
    assert list(result.concepts) == [OPEN, CLOSE]
    # frames 5..9 of episode 0 come before its window 9..29
    assert [r.segment_id for r in result.concepts[OPEN]] == [2, 4]
    assert [r.segment_id for r in result.concepts[CLOSE]] == [1, 3, 0]  # episodes 1, 4, 6
    assert result.repo_id == "lab/other"


def test_rename_map(root, rows, manifest_path, tmp_path, caplog):
    rename = {OPEN: "drawer", CLOSE: "shut", "turn on the stove": "stove"}
    with caplog.at_level(logging.WARNING, logger="steering_core.data.concept_map"):
        renamed = build_concept_map(manifest_path, root, rename=rename)
    assert "rename entries for tasks not in the manifest: ['turn on the stove']" in caplog.text
    assert set(renamed.concept_count) == {"drawer", "shut"} and sum(renamed.concept_count.values()) == 6
    assert renamed.model_dump(mode="json")["concepts"] == brute_force_map(manifest_path, rows, rename)
    starts = [r.start_index for r in renamed.concepts["drawer"]]
    assert starts == sorted(starts)
    for merging in ({OPEN: "drawer", CLOSE: "drawer"}, {OPEN: CLOSE}, {OPEN: "Drawer", CLOSE: "drawer "}):
        with pytest.raises(ValueError, match="one concept .* which would merge their rows"):
            build_concept_map(manifest_path, root, rename=merging)

    (tmp_path / "list.json").write_text('["open"]')
    with pytest.raises(ValueError, match="list.json: expected a JSON object of task text -> concept name, found list"):
        read_rename_map(tmp_path / "list.json")
    (tmp_path / "bad.json").write_text(json.dumps({OPEN: 3, CLOSE: ""}))
    with pytest.raises(ValueError, match=rf"non-empty strings; check the entries for \['{CLOSE}', '{OPEN}'\]"):
        read_rename_map(tmp_path / "bad.json")


def test_reference_concept_map_loads_unchanged(tmp_path):
    original = json.loads(REFERENCE.read_text())
    loaded = read_concept_map(REFERENCE)
    assert loaded.sample_count == 22259 and loaded.concept_count == original["concept_count"]
    assert loaded.model_dump(mode="json") == original
    assert all(list(row) == ROW_FIELDS for rows in original["concepts"].values() for row in rows)
    write_concept_map(loaded, tmp_path / "again.json")
    assert json.loads((tmp_path / "again.json").read_text()) == original


def test_invalid_concept_map_file(tmp_path):
    payload = json.loads(REFERENCE.read_text())
    payload["concept_count"][OPEN] = 49
    payload["concepts"][CLOSE][0]["length"] = 70
    path = tmp_path / "bad.json"
    path.write_text(json.dumps(payload))
    with pytest.raises(ValueError) as err:
        read_concept_map(path)
    assert str(err.value).startswith(f"{path}: not a valid concept map")
    assert f"concept_count['{OPEN}'] is 49, but it has 50 rows" in str(err.value)
    assert f"concepts['{CLOSE}'] segment 50: length 70, expected end_index - start_index + 1" in str(err.value)


def test_manifest_of_another_dataset(root, tmp_path):
    with pytest.raises(ValueError) as err:
        build_concept_map(REFERENCE_MANIFEST, root)
    message = str(err.value)
    assert message.startswith(f"{REFERENCE_MANIFEST} does not match the dataset {root}: ")
    assert "segments[0] (episode_000050): episode 50 is not in the dataset (7 episodes)" in message
    assert "segments[57] (episode_000007): episode 7 is not in the dataset (7 episodes)" in message
    assert f"segments[50] (episode_000000): task '{CLOSE}', but episode 0 shows '{OPEN}'" in message
    assert "segments[51] (episode_000001): frames 16..72 outside episode 1's frames 0..25" in message
    assert message.count("is not in the dataset") == 50 + 43
    assert message.endswith("Rebuild the manifest from this dataset with `latent-steering manifest`.")


def test_fingerprint_of_another_dataset(root, manifest_path, tmp_path):
    changed = shutil.copytree(root, tmp_path / "changed")
    info = json.loads((changed / "meta/info.json").read_text())
    info["fps"] = 20
    (changed / "meta/info.json").write_text(json.dumps(info))
    with pytest.raises(ValueError, match=r"the manifest was built from a dataset with fingerprint [0-9a-f]{12}\.\.\., "
                                         r"this one has [0-9a-f]{12}\.\.\. \(another dataset, or this one "
                                         r"changed since\)"):
        build_concept_map(manifest_path, changed)


def test_bad_segments(root, manifest_path, tmp_path):
    def damage(payload):
        del payload["dataset"]  # a seed manifest: no fingerprint to compare, so each segment is checked
        first = payload["segments"][0]  # episode 0, 30 frames
        first["end_step"] = 33
        first["axis_values"] += [0.0] * (33 - len(first["axis_values"]) - first["start_step"] + 1)
        payload["segments"][1]["episode_index"] = 99
        payload["segments"][2]["episode_index"] = 1  # an OPEN segment on a CLOSE episode
        payload["segments"][3]["episode_index"] = None

    path = edit_manifest(manifest_path, tmp_path / "bad.json", damage)
    with pytest.raises(ValueError) as err:
        build_concept_map(path, root)
    message = str(err.value)
    start = json.loads(path.read_text())["segments"][0]["start_step"]
    assert f"segments[0] (episode_000000): frames {start}..33 outside episode 0's frames 0..29" in message
    assert "segments[1] (episode_000003): episode 99 is not in the dataset (7 episodes)" in message
    assert f"segments[2] (episode_000005): task '{OPEN}', but episode 1 shows '{CLOSE}'" in message
    assert "segments[3] (episode_000001): no episode_index and data/chunk-000/file-000.parquet:episode_000001 is " \
        "not in the dataset's meta/libero_sources.json" in message

    empty = edit_manifest(manifest_path, tmp_path / "empty.json", lambda p: p.update(segments=[]))
    with pytest.raises(ValueError, match="empty.json: the manifest has no segments; rebuild it"):
        build_concept_map(empty, root)


def test_frames_missing_from_the_data(root, manifest_path, tmp_path):
    holed = shutil.copytree(root, tmp_path / "holed")
    path = holed / "data/chunk-000/file-001.parquet"
    table = pq.read_table(path)
    hole = pc.and_(pc.equal(table["episode_index"], 4), pc.equal(table["frame_index"], 20))
    pq.write_table(table.filter(pc.invert(hole)), path)
    seed_manifest = edit_manifest(manifest_path, tmp_path / "seed.json", lambda p: p.pop("dataset"))
    with pytest.raises(ValueError) as err:
        build_concept_map(seed_manifest, holed)
    message = str(err.value)
    segment = json.loads(seed_manifest.read_text())["segments"][4]
    assert segment["episode_index"] == 4
    frames = sum(e.length for e in read_meta(holed).episodes)
    assert message == (f"{holed}: the data files hold {frames - 1} frames, but {holed / 'meta/episodes'} lists "
                       f"{frames}; re-create the dataset")  # refused before any segment is located


def test_cli_concept_map(root, rows, manifest_path, tmp_path):
    rename = tmp_path / "rename.json"
    rename.write_text(json.dumps({OPEN: "open", CLOSE: "close"}))
    output = tmp_path / "maps" / "open_vs_close_concept_map.json"
    result = CliRunner().invoke(app, [
        "concept-map", "--manifest-path", str(manifest_path), "--output-path", str(output),
        "--lerobot-root", str(root), "--repo-id", "lab/contrast", "--concept-map", str(rename),
    ])
    assert result.exit_code == 0, result.output
    written = json.loads(output.read_text())
    assert list(written) == ["manifest", "lerobot_root", "repo_id", "concept_count", "sample_count", "concepts"]
    assert written["concepts"] == brute_force_map(manifest_path, rows, {OPEN: "open", CLOSE: "close"})
    assert written["repo_id"] == "lab/contrast"
    samples = sum(r["length"] for r in written["concepts"]["open"])
    assert f"wrote {output} (192 frames in the dataset)" in result.output
    assert f"'open': 3 segment(s), {samples} sample(s)" in result.output


def test_cli_errors_write_nothing(root, tmp_path):
    output = tmp_path / "map.json"
    result = CliRunner().invoke(app, [
        "concept-map", "--manifest-path", str(REFERENCE_MANIFEST), "--output-path", str(output),
        "--lerobot-root", str(root),
    ])
    assert result.exit_code == 1
    assert result.output.startswith(f"error: {REFERENCE_MANIFEST} does not match the dataset {root}")
    result = CliRunner().invoke(app, [
        "concept-map", "--manifest-path", str(tmp_path / "none.json"), "--output-path", str(output),
        "--lerobot-root", str(root),
    ])
    assert result.exit_code == 1 and "none.json: file not found" in result.output
    assert list(tmp_path.iterdir()) == []
