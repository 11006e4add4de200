"""LeRobot v2.x: our v2.1 writer, read back by our reader, by lerobot's own converter, and end to end.

The same LIBERO demos are converted twice, to v3.0 through lerobot and to v2.1 through
`v21_writer`; everything read from the v2.1 copy (read-only, as a Hugging Face cache is) must equal
what the v3.0 copy gives, and lerobot 0.4.4's v2.1 -> v3.0 converter must accept it.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import stat
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
import torch
from helpers_libero import tiny_task
from safetensors.torch import load_file

from steering_core.capture import CaptureSettings, capture
from steering_core.capture.slicing import SliceSettings, slice_concepts
from steering_core.data.concept_map import build_concept_map, write_concept_map
from steering_core.data.contrast import build_manifest, write_manifest
from steering_core.data.convert import ConvertSettings, convert_libero
from steering_core.data.dataset import dataset_fingerprint, read_episode_columns, read_index_columns, read_meta
from steering_core.data.v2_frames import V2Frames
from steering_core.data.v21_writer import V21Writer
from steering_core.pi05.spec import ModelSpec
from steering_core.synthetic.libero import SyntheticSettings, write_libero_file
from steering_core.synthetic.pi05 import tiny_arch, write_pi05_checkpoint
from steering_core.synthetic.sae import write_sae_folder
from steering_core.synthetic.tokenizer import write_tokenizer
from steering_core.vectors.directions import SteeringSettings, compute_steering

os.environ.setdefault("HF_HUB_OFFLINE", "1")

OPEN = "open the top drawer of the cabinet"
CLOSE = "close the top drawer of the cabinet"
DEMOS = SyntheticSettings(image_size=16, num_steps=10, length_jitter=4, state_dim=12)
FIXTURES = Path(__file__).parent / "fixtures" / "lerobot_v21"
ARCH = tiny_arch()


def make_read_only(root: Path) -> None:
    """chmod a-w the whole tree, as a shared Hugging Face cache may be."""
    for path in [*root.rglob("*"), root]:
        path.chmod(path.stat().st_mode & ~(stat.S_IWUSR | stat.S_IWGRP | stat.S_IWOTH))


def make_writable(root: Path) -> None:
    for path in [root, *root.rglob("*")]:
        path.chmod(path.stat().st_mode | stat.S_IWUSR)


def tree_listing(root: Path) -> dict[str, int]:
    return {p.relative_to(root).as_posix(): p.stat().st_mtime_ns for p in root.rglob("*")}


@pytest.fixture(scope="module")
def datasets(tmp_path_factory):
    """The same demos as v3.0 (lerobot) and v2.1 (ours, then read-only): (v30 root, v21 root)."""
    root = tmp_path_factory.mktemp("v2")
    demos = root / "demos"
    demos.mkdir()
    write_libero_file(demos, tiny_task(OPEN, axis=2, direction=1), num_demos=3, settings=DEMOS)
    write_libero_file(demos, tiny_task(CLOSE, axis=2, direction=-1), num_demos=3, settings=DEMOS)
    v30 = root / "v30" / "libero"
    v21 = root / "v21" / "libero"
    convert_libero([demos], v30, ConvertSettings(repo_id="local/libero", image_size=16))
    convert_libero([demos], v21, ConvertSettings(repo_id="local/libero", image_size=16, codebase_version="v2.1"))
    make_read_only(v21)
    yield v30, v21
    make_writable(v21)


def lerobot_items(root: Path, repo_id: str = "local/libero") -> list[dict]:
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    dataset = LeRobotDataset(repo_id, root=root)
    return [dataset[i] for i in range(len(dataset))]


def assert_items_equal(ours: list[dict], theirs: list[dict], keys=("image", "wrist_image", "state", "actions")):
    assert len(ours) == len(theirs)
    for a, b in zip(ours, theirs, strict=True):
        for key in keys:
            assert a[key].dtype == b[key].dtype and torch.equal(a[key], b[key]), key
        for key in ("index", "episode_index", "frame_index", "task_index"):
            assert int(a[key]) == int(b[key]), key
        assert a["task"] == b["task"]


# ----------------------------------------------------------------------------- reading


def test_v21_reads_back_equal_to_the_v30_conversion(datasets):
    v30, v21 = datasets
    before = tree_listing(v21)
    meta30, meta21 = read_meta(v30), read_meta(v21)
    assert (meta21.version, meta30.version) == ("v2.1", "v3.0")
    assert meta21.tasks == meta30.tasks
    fields = ("episode_index", "tasks", "length", "from_index", "to_index")
    assert [[getattr(e, f) for f in fields] for e in meta21.episodes] == [
        [getattr(e, f) for f in fields] for e in meta30.episodes]
    assert [e.data_file for e in meta21.episodes] == [
        f"data/chunk-000/episode_{i:06d}.parquet" for i in range(6)]
    columns30, columns21 = read_index_columns(v30), read_index_columns(v21)
    for name in ("episode_index", "frame_index", "index", "task_index"):
        np.testing.assert_array_equal(getattr(columns21, name), getattr(columns30, name))
    for column in ("state", "actions"):
        ours, theirs = read_episode_columns(v21, range(6), column), read_episode_columns(v30, range(6), column)
        for episode in range(6):
            np.testing.assert_array_equal(ours[episode], theirs[episode])
    frames = V2Frames(meta21, range(6))
    assert_items_equal([frames[i] for i in range(len(frames))], lerobot_items(v30))
    assert len(dataset_fingerprint(v21)) == 64
    assert tree_listing(v21) == before  # read in place: nothing written, touched or added


def test_v21_layout_is_openpi_s(datasets):
    _, v21 = datasets
    info = json.loads((v21 / "meta/info.json").read_text())
    reference = json.loads((FIXTURES / "info.json").read_text())
    assert list(info) == list(reference)
    assert {k: v for k, v in info.items() if k not in ("features", "total_episodes", "total_frames", "splits")} == {
        k: v for k, v in reference.items() if k not in ("features", "total_episodes", "total_frames", "splits")}
    assert list(info["features"]) == list(reference["features"])
    assert info["features"]["state"] == reference["features"]["state"]
    assert info["features"]["image"] == {**reference["features"]["image"], "shape": [16, 16, 3]}
    assert info["splits"] == {"train": "0:6"} and info["total_episodes"] == 6
    table = pq.read_table(v21 / "data/chunk-000/episode_000000.parquet")
    assert table.schema.metadata[b"huggingface"].decode() == (FIXTURES / "huggingface.json").read_text().strip()
    assert table.schema.field("image").type == pa.struct([("bytes", pa.binary()), ("path", pa.string())])
    assert table.schema.field("state").type == pa.list_(pa.field("element", pa.float32()), 8)
    assert table.column("image")[1].as_py()["path"] == "frame_000001.png"
    assert table.column("timestamp").type == pa.float32()
    stats = [json.loads(line) for line in (v21 / "meta/episodes_stats.jsonl").read_text().splitlines()]
    assert [s["episode_index"] for s in stats] == list(range(6))
    assert list(stats[0]["stats"]) == list(reference["features"])
    assert list(stats[0]["stats"]["state"]) == ["min", "max", "mean", "std", "count"]


def test_writer_reproduces_lerobot_s_meta_files(tmp_path):
    """The fixtures are lerobot's v2.1 output for these seeded frames (3 episodes, 12/130/7 frames), written by
    tests/fixtures/make_lerobot_v21.py (GENERATOR.json names the lerobot release)."""
    features = {
        "image": {"dtype": "image", "shape": (256, 256, 3), "names": ["height", "width", "channel"]},
        "wrist_image": {"dtype": "image", "shape": (256, 256, 3), "names": ["height", "width", "channel"]},
        "state": {"dtype": "float32", "shape": (8,), "names": ["state"]},
        "actions": {"dtype": "float32", "shape": (7,), "names": ["actions"]},
    }
    writer = V21Writer.create(tmp_path, fps=10, robot_type="panda", features=features)
    rng = np.random.default_rng(0)
    for length, task in [(12, "put the bowl on the plate"), (130, "open the drawer"), (7, "put the bowl on the plate")]:
        frames = [(rng.integers(0, 256, (256, 256, 3), dtype=np.uint8), rng.integers(0, 256, (256, 256, 3), dtype=np.uint8),
                   rng.standard_normal(8).astype(np.float32), rng.standard_normal(7).astype(np.float32))
                  for _ in range(length)]
        columns = {key: np.stack([f[i] for f in frames]) for i, key in enumerate(features)}
        writer.add_episode(columns, task)
    for name in ("info.json", "tasks.jsonl", "episodes.jsonl"):
        assert (tmp_path / "meta" / name).read_bytes() == (FIXTURES / name).read_bytes(), name
    ours = [json.loads(line) for line in (tmp_path / "meta/episodes_stats.jsonl").read_text().splitlines()]
    theirs = [json.loads(line) for line in (FIXTURES / "episodes_stats.jsonl").read_text().splitlines()]
    assert [list(o["stats"]) for o in ours] == [list(t["stats"]) for t in theirs]
    for o, t in zip(ours, theirs, strict=True):
        for feature, values in t["stats"].items():
            for name, expected in values.items():  # image std differs in the last bits across numpy versions
                np.testing.assert_allclose(o["stats"][feature][name], expected, rtol=1e-12, err_msg=f"{feature}/{name}")
    assert pq.ParquetFile(tmp_path / "data/chunk-000/episode_000001.parquet").metadata.num_row_groups == 2  # 100 + 30


def test_fixtures_record_the_lerobot_that_wrote_them():
    for folder in (FIXTURES, FIXTURES.parent / "lerobot_v21_video"):
        record = json.loads((folder / "GENERATOR.json").read_text())
        assert record["generator"] == "tests/fixtures/make_lerobot_v21.py" and record["codebase_version"] == "v2.1"
        assert re.fullmatch(r"\d+\.\d+\.\d+\S*", record["versions"]["lerobot"]), record


def test_v20_without_stats_reads(datasets, tmp_path):
    _, v21 = datasets
    v20 = tmp_path / "v20"
    shutil.copytree(v21, v20)
    make_writable(v20)
    (v20 / "meta/episodes_stats.jsonl").unlink()
    info = json.loads((v20 / "meta/info.json").read_text())
    (v20 / "meta/info.json").write_text(json.dumps({**info, "codebase_version": "v2.0"}, indent=4))
    meta = read_meta(v20)
    assert meta.version == "v2.0" and meta.episodes == read_meta(v21).episodes
    np.testing.assert_array_equal(read_index_columns(v20).index, read_index_columns(v21).index)
    assert dataset_fingerprint(v20) != dataset_fingerprint(v21)
    frames20, frames21 = V2Frames(meta, [4]), V2Frames(read_meta(v21), [4])
    assert_items_equal([frames20[i] for i in range(len(frames20))], [frames21[i] for i in range(len(frames21))])


def test_many_chunks(datasets, tmp_path):
    """openpi's 1,693 episodes span chunk-000 and chunk-001; chunks of 2 episodes show the same here."""
    v30, v21 = datasets
    chunked = tmp_path / "chunked"
    shutil.copytree(v21, chunked)
    make_writable(chunked)
    info = json.loads((chunked / "meta/info.json").read_text())
    (chunked / "meta/info.json").write_text(json.dumps({**info, "chunks_size": 2, "total_chunks": 3}, indent=4))
    for episode in range(6):
        source = chunked / f"data/chunk-000/episode_{episode:06d}.parquet"
        target = chunked / f"data/chunk-{episode // 2:03d}/episode_{episode:06d}.parquet"
        target.parent.mkdir(exist_ok=True)
        source.rename(target)
    meta = read_meta(chunked)
    assert [e.data_file for e in meta.episodes][4] == "data/chunk-002/episode_000004.parquet"
    np.testing.assert_array_equal(read_index_columns(chunked).index, read_index_columns(v30).index)
    frames = V2Frames(meta, range(6))
    assert_items_equal([frames[i] for i in range(len(frames))], lerobot_items(v30))


def test_unsupported_versions_are_named(datasets, tmp_path):
    _, v21 = datasets
    bad = tmp_path / "v16"
    shutil.copytree(v21 / "meta", bad / "meta")
    make_writable(bad)
    info = json.loads((bad / "meta/info.json").read_text())
    (bad / "meta/info.json").write_text(json.dumps({**info, "codebase_version": "v1.6"}))
    with pytest.raises(ValueError, match=r"`codebase_version` is 'v1.6', expected one of \['v2.0', 'v2.1', 'v3.0'\]"):
        read_meta(bad)
    (bad / "meta/info.json").write_text(json.dumps({k: v for k, v in info.items() if k != "chunks_size"}))
    with pytest.raises(ValueError, match=r"missing field\(s\) \['chunks_size'\]"):
        read_meta(bad)
    (bad / "meta/info.json").write_text(json.dumps(info))
    (bad / "meta/episodes.jsonl").write_text('{"episode_index": 0, "length": 3}\n')
    with pytest.raises(ValueError, match=r"episodes.jsonl:1: expected an object with keys \['episode_index', 'tasks'"):
        read_meta(bad)


def lerobot_convert_v21(repo_id: str, parent: Path) -> None:
    """Convert the v2.1 dataset at `parent / repo_id` to v3.0 in place with lerobot's own converter, offline.

    lerobot 0.4 has it in `lerobot.datasets.v30` and reads `root` as the folder above the dataset (the dataset at
    `root / repo_id`); lerobot 0.5.0 reads `root` as the dataset folder itself, and 0.5.1 moved the module to
    `lerobot.scripts`.
    """
    from importlib.metadata import version

    from packaging.version import Version

    try:
        from lerobot.scripts.convert_dataset_v21_to_v30 import convert_dataset
    except ModuleNotFoundError:
        from lerobot.datasets.v30.convert_dataset_v21_to_v30 import convert_dataset
    root = parent / repo_id if Version(version("lerobot")) >= Version("0.5") else parent
    convert_dataset(repo_id=repo_id, root=str(root), push_to_hub=False)


def test_lerobot_converter_accepts_our_v21(datasets, tmp_path):
    """A second, independent reader: lerobot's v2.1 -> v3.0 converter, then LeRobotDataset."""
    v30, v21 = datasets
    target = tmp_path / "local" / "ours"
    shutil.copytree(v21, target)
    make_writable(target)
    assert not (tmp_path / "local" / "ours_old").exists()  # the converter would restore a stale copy from it
    lerobot_convert_v21("local/ours", tmp_path)
    assert json.loads((target / "meta/info.json").read_text())["codebase_version"] == "v3.0"
    assert_items_equal(lerobot_items(target, "local/ours"), lerobot_items(v30))


# ----------------------------------------------------------------------------- end to end


def pipeline(root: Path, dataset: Path, checkpoint: Path, tokenizer: Path, sae: Path, num_workers: int) -> dict[str, Path]:
    manifest = write_manifest(build_manifest(dataset, OPEN, CLOSE, repo_id="local/libero"), root / "manifest.json")
    concept_map = write_concept_map(build_concept_map(manifest, dataset, repo_id="local/libero"), root / "map.json")
    settings = CaptureSettings(model=ModelSpec(checkpoint=checkpoint, tokenizer=tokenizer, arch=ARCH), layers=(1,),
                               batch_size=4, device="cpu", num_workers=num_workers)
    capture(dataset, "local/libero", root / "run", settings)
    slice_concepts(root / "run", concept_map, root / "slices", SliceSettings(layers=(1,)))
    pairs = {"pairs": [{"name": "open_vs_close", "positive_label": OPEN, "positive_path": f"slices/layer01/{OPEN}.pt",
                        "negative_label": CLOSE, "negative_path": f"slices/layer01/{CLOSE}.pt"}]}
    (root / "pairs.json").write_text(json.dumps(pairs))
    steering = compute_steering(SteeringSettings(pairs_config=root / "pairs.json", output_root=root / "steer", layer=1,
                                                 sae=str(sae), device="cpu", batch_size=16))
    return {"manifest": manifest, "run": root / "run", "slices": root / "slices" / "layer01",
            "vectors": steering / "open_vs_close"}


def test_pipeline_on_v21_equals_v30(datasets, tmp_path):
    v30, v21 = datasets
    checkpoint = write_pi05_checkpoint(tmp_path / "checkpoint", ARCH)
    tokenizer = write_tokenizer(tmp_path / "tokenizer.model")
    sae = write_sae_folder(tmp_path / "sae", d_in=ARCH.width, d_sae=32, hook_layer=1)
    a = pipeline(tmp_path / "a", v30, checkpoint, tokenizer, sae, num_workers=0)
    b = pipeline(tmp_path / "b", v21, checkpoint, tokenizer, sae, num_workers=1)  # V2Frames through a worker process
    manifest_a, manifest_b = (json.loads(r["manifest"].read_text()) for r in (a, b))
    segments = [{k: v for k, v in s.items() if k != "file"} for s in manifest_a["segments"]]
    assert segments == [{k: v for k, v in s.items() if k != "file"} for s in manifest_b["segments"]]
    assert manifest_a["axis"] == manifest_b["axis"]
    for segment in manifest_b["segments"]:  # the seed's `file`: the per-episode parquet holding the episode
        assert (v21 / segment["file"]).is_file() and segment["file"].endswith(f"{segment['demo']}.parquet")
    shards_a = sorted((a["run"] / "instructions/layer01").glob("*.safetensors"))
    shards_b = sorted((b["run"] / "instructions/layer01").glob("*.safetensors"))
    assert [p.name for p in shards_a] == [p.name for p in shards_b] and shards_a
    for pa_, pb_ in zip(shards_a, shards_b, strict=True):
        ta, tb = load_file(pa_), load_file(pb_)
        assert ta.keys() == tb.keys() and all(torch.equal(ta[k], tb[k]) for k in ta)
    slices_a = sorted(a["slices"].glob("*.safetensors"))
    assert [p.name for p in slices_a] == [p.name for p in sorted(b["slices"].glob("*.safetensors"))] and slices_a
    for path in slices_a:
        ta, tb = load_file(path), load_file(b["slices"] / path.name)
        assert all(torch.equal(ta[k], tb[k]) for k in ta)
    vectors = sorted(a["vectors"].glob("*.safetensors"))
    assert {p.stem for p in vectors} >= {"latent_direction", "residual_direction"}
    for path in vectors:
        ta, tb = load_file(path), load_file(b["vectors"] / path.name)
        assert all(torch.equal(ta[k], tb[k]) for k in ta)
        assert ta[next(iter(ta))].abs().sum() > 0


def test_video_frames_equal_lerobot_s(tmp_path):
    """A v2.1 video dataset lerobot wrote (AV1, 64x96, 2 x 15 frames; make_lerobot_v21.py): our frames are lerobot's."""
    fixture = Path(__file__).parent / "fixtures" / "lerobot_v21_video"
    ours = V2Frames(read_meta(fixture), [0, 1], video_backend="pyav")
    items = [ours[i] for i in range(len(ours))]
    camera = "observation.images.cam"
    assert items[17][camera].shape == (3, 64, 96) and items[17][camera].dtype == torch.float32
    assert [int(item["frame_index"]) for item in items[13:17]] == [13, 14, 0, 1]
    shutil.copytree(fixture, tmp_path / "u" / "vid")
    lerobot_convert_v21("u/vid", tmp_path)
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    theirs = LeRobotDataset("u/vid", root=tmp_path / "u" / "vid", video_backend="pyav")
    assert len(theirs) == len(items)
    for position, item in enumerate(items):
        expected = theirs[position]
        assert torch.equal(item[camera], expected[camera]), position
        assert torch.equal(item["state"], expected["state"]) and item["task"] == expected["task"]


def test_appending_to_a_v21_dataset_equals_converting_at_once(tmp_path):
    demos = tmp_path / "demos"
    demos.mkdir()
    settings = ConvertSettings(repo_id="local/libero", image_size=16, codebase_version="v2.1")
    write_libero_file(demos, tiny_task(CLOSE, axis=2, direction=-1), num_demos=2, settings=DEMOS)
    assert convert_libero([demos], tmp_path / "grown", settings).action == "created"
    write_libero_file(demos, tiny_task(OPEN, axis=2, direction=1), num_demos=2, settings=DEMOS)  # sorts after CLOSE
    assert convert_libero([demos], tmp_path / "grown", settings).action == "appended"
    convert_libero([demos], tmp_path / "once", settings)
    grown, once = tmp_path / "grown", tmp_path / "once"
    files = sorted(p.relative_to(once) for p in once.rglob("*") if p.is_file())
    assert files == sorted(p.relative_to(grown) for p in grown.rglob("*") if p.is_file())
    for name in files:
        if name.suffix == ".parquet":
            assert pq.read_table(grown / name).equals(pq.read_table(once / name)), name
        else:
            assert (grown / name).read_bytes() == (once / name).read_bytes(), name
    assert json.loads((grown / "meta/info.json").read_text())["total_tasks"] == 2


def test_a_hugging_face_cache_layout_reads(datasets, tmp_path):
    """The hub cache keeps files as blobs and a snapshot folder of symlinks to them; read in place, read-only."""
    v30, v21 = datasets
    blobs, snapshot = tmp_path / "blobs", tmp_path / "snapshots" / "0123abc"
    blobs.mkdir()
    for number, path in enumerate(sorted(p for p in v21.rglob("*") if p.is_file())):
        blob = blobs / f"blob{number:03d}"
        shutil.copyfile(path, blob)
        link = snapshot / path.relative_to(v21)
        link.parent.mkdir(parents=True, exist_ok=True)
        link.symlink_to(os.path.relpath(blob, link.parent))
    make_read_only(tmp_path)
    try:
        assert dataset_fingerprint(snapshot) == dataset_fingerprint(v21)
        np.testing.assert_array_equal(read_index_columns(snapshot).index, read_index_columns(v30).index)
        frames = V2Frames(read_meta(snapshot), [5])
        assert_items_equal([frames[i] for i in range(len(frames))], lerobot_items(v30)[-len(frames):])
    finally:
        make_writable(tmp_path)
