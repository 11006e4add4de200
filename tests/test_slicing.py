"""Slicing: per-concept tensors equal a brute-force selection; options and errors."""

from __future__ import annotations

import json

import pytest
import torch
from helpers_locks import hold_output_lock, start_waiting
from helpers_zip import assert_same_torch_records
from safetensors.torch import load_file, save_file

from steering_core.capture import shards
from steering_core.capture.slicing import SliceSettings, safe_file_name, slice_concepts, slice_file_names

WIDTH = 6
LAYERS = (2, 5)
# episode -> (frames, task); the two tasks have instruction spans of different lengths
EPISODES = {0: (7, "open the drawer"), 1: (5, "close the drawer"), 2: (6, "open the drawer"), 3: (4, "close it")}
SPAN = {"open the drawer": (769, 770, 771), "close the drawer": (769, 770), "close it": (769,)}
OPEN, CLOSE = "open the top/drawer", "close the drawer"


def first_index(episode: int) -> int:
    return sum(EPISODES.get(e, (0,))[0] for e in range(episode))


def build_run(run_dir, episodes_per_shard=2, token_type="instructions", sources=None, storage_dtype="float32",
              first=first_index) -> None:
    """Write a run of every episode and layer with rows that encode where they come from.

    `first(episode)` is the dataset index of the episode's first frame.
    """
    spec = shards.RunSpec(token_type=token_type, layers=LAYERS, width=WIDTH, episodes_per_shard=episodes_per_shard,
                          storage_dtype=storage_dtype, inputs={"checkpoint": "tiny"}, sources=sources or {})
    shards.write_run_spec(run_dir, spec)
    generator = torch.Generator().manual_seed(0)
    for key, members in shards.group_episodes(EPISODES, episodes_per_shard).items():
        for layer in LAYERS:
            columns = {name: [] for name in shards.ROW_COLUMNS}
            for episode in members:
                frames, task = EPISODES[episode]
                for frame in range(frames):
                    for token, position in enumerate(SPAN[task]):
                        columns["index"].append(first(episode) + frame)
                        columns["episode_index"].append(episode)
                        columns["frame_index"].append(frame)
                        columns["token_position"].append(position)
                        columns["token_id"].append(100 + token)
            n = len(columns["index"])
            rows = shards.ShardRows(residuals=torch.randn(n, WIDTH, generator=generator),
                                    **{k: torch.tensor(v) for k, v in columns.items()})
            shards.write_shard(run_dir, spec, layer, key, rows, episodes=members, inputs="x")
    shards.write_run_metadata(run_dir)


def segment(episode: int, start: int, end: int, **overrides) -> dict:
    fields = dict(segment_id=episode, episode_index=episode, frame_start=start, frame_end=end,
                  observed_frame_start=start, observed_frame_end=end, start_index=first_index(episode) + start,
                  end_index=first_index(episode) + end, length=end - start + 1)
    return fields | overrides


def write_concept_map(path, concepts: dict[str, list[dict]]):
    payload = {
        "manifest": "manifests/test.json", "lerobot_root": "libero_lerobot/test", "repo_id": "test",
        "concept_count": {name: len(segments) for name, segments in concepts.items()},
        "sample_count": 1000,  # frames of the dataset the map claims to describe
        "concepts": concepts,
    }
    path.write_text(json.dumps(payload))
    return path


@pytest.fixture()
def run_dir(tmp_path):
    build_run(tmp_path / "run")
    return tmp_path / "run"


@pytest.fixture()
def concept_map(tmp_path):
    return write_concept_map(tmp_path / "map.json", {
        OPEN: [segment(0, 1, 4), segment(2, 0, 5), segment(0, 3, 6)],  # overlapping segments count once
        CLOSE: [segment(1, 2, 4), segment(3, 0, 1)],
    })


def brute_force(run_dir, concept_map_path, layer, with_columns=False):
    """Load every shard whole and pick rows with python loops: concept -> (rows, [(index, position)]).

    With `with_columns`, concept -> (float32 rows, keys, {column: (rows,) int64 tensor}).
    """
    concepts = json.loads(concept_map_path.read_text())["concepts"]
    found = {name: [] for name in concepts}
    for path in sorted((run_dir / "instructions" / f"layer{layer:02d}").glob("*.safetensors")):
        data = load_file(path)
        for row in range(data["residuals"].shape[0]):
            episode, frame = int(data["episode_index"][row]), int(data["frame_index"][row])
            for name, segments in concepts.items():
                if any(s["episode_index"] == episode and s["frame_start"] <= frame <= s["frame_end"]
                       for s in segments):
                    key = (int(data["index"][row]), int(data["token_position"][row]))
                    columns = {column: int(data[column][row]) for column in shards.ROW_COLUMNS}
                    found[name].append((key, data["residuals"][row], columns))
    result = {}
    for name, items in found.items():
        items.sort(key=lambda item: item[0])
        rows, keys = torch.stack([r for _, r, _ in items]), [k for k, _, _ in items]
        columns = {column: torch.tensor([c[column] for _, _, c in items]) for column in shards.ROW_COLUMNS}
        result[name] = (rows.float(), keys, columns) if with_columns else (rows, keys)
    return result


def test_token_slices_equal_brute_force(tmp_path, run_dir, concept_map):
    out = tmp_path / "slices"
    calls = []
    written = slice_concepts(run_dir, concept_map, out, SliceSettings(layers=LAYERS),
                             progress=lambda done, total: calls.append((done, total)))
    assert calls == [(i, 4) for i in range(1, 5)]  # two shards (two episodes each) per layer
    assert written == {layer: out / f"layer{layer:02d}" / "index.json" for layer in LAYERS}
    for layer in LAYERS:
        expected = brute_force(run_dir, concept_map, layer)
        index = json.loads(written[layer].read_text())
        assert index["concepts"][OPEN]["pt"] == "open the top_drawer.pt"
        assert index["run_fingerprint"] == shards.read_run_metadata(run_dir).run_fingerprint
        for name, (rows, keys) in expected.items():
            entry = index["concepts"][name]
            tensor = torch.load(out / f"layer{layer:02d}" / entry["pt"], weights_only=True)
            assert tensor.dtype == torch.float32 and tensor.shape == (len(keys), WIDTH)
            assert torch.equal(tensor, rows)
            copy = load_file(out / f"layer{layer:02d}" / entry["safetensors"])
            assert torch.equal(copy["residuals"], rows)
            assert list(zip(copy["index"].tolist(), copy["token_position"].tolist())) == keys
            assert entry["rows"] == len(keys)
            assert [s["episode_index"] for s in entry["segments"]] == \
                [s["episode_index"] for s in json.loads(concept_map.read_text())["concepts"][name]]
    # OPEN: episode 0 frames 1-6 and episode 2 frames 0-5, three instruction tokens each
    assert json.loads(written[2].read_text())["concepts"][OPEN]["rows"] == (6 + 6) * 3


@pytest.mark.parametrize("storage_dtype", ["float32", "bfloat16"])
@pytest.mark.parametrize("reversed_index", [False, True])
@pytest.mark.parametrize("reading", ["checked", "checked in 2-row reads", "unchecked in 2-row reads"])
def test_slice_files_are_byte_identical_to_saving_the_selected_rows(
        tmp_path, monkeypatch, storage_dtype, reversed_index, reading):
    """Each .safetensors equals, byte for byte, what save_file writes for the selected rows, and each .pt holds the
    records torch.save writes for them.

    With `reversed_index` the later episodes come first in the dataset, so shard order is not dataset order. Shards
    are read whole when checked, only the span the concepts need when not, and with 2-row reads a concept's rows
    and frames straddle the reads.
    """
    from steering_core.capture import slicing

    if "2-row" in reading:
        monkeypatch.setattr(slicing, "_BUFFER_BYTES", 2 * WIDTH * 4)
    verify = reading.startswith("checked")

    def reversed_first(episode):
        return sum(EPISODES[e][0] for e in EPISODES if e > episode)

    first = reversed_first if reversed_index else first_index
    build_run(tmp_path / "run", episodes_per_shard=3, storage_dtype=storage_dtype, first=first)
    concepts = {OPEN: [segment(e, 1, 4, start_index=first(e) + 1, end_index=first(e) + 4) for e in (0, 2)],
                CLOSE: [segment(e, 0, 3, start_index=first(e), end_index=first(e) + 3) for e in (1, 3)]}
    concept_map = write_concept_map(tmp_path / "map.json", concepts)
    settings = SliceSettings(layers=(5,), verify_checksums=verify)
    slice_concepts(tmp_path / "run", concept_map, tmp_path / "slices", settings)
    slice_concepts(tmp_path / "run", concept_map, tmp_path / "frames", settings.model_copy(update={"reduce": "frame"}))
    expected_dir = tmp_path / "expected"
    expected_dir.mkdir()
    for name, (rows, keys, columns) in brute_force(tmp_path / "run", concept_map, 5, with_columns=True).items():
        stem = safe_file_name(name)
        assert keys == sorted(keys) and len(keys) > 4
        # reduce=token: the rows themselves
        torch.save(rows, expected_dir / f"{stem}.pt")
        save_file({"residuals": rows, **columns}, expected_dir / f"{stem}.safetensors")
        written = tmp_path / "slices" / "layer05" / stem
        assert written.with_suffix(".safetensors").read_bytes() == (expected_dir / f"{stem}.safetensors").read_bytes()
        assert_same_torch_records(written.with_suffix(".pt"), expected_dir / f"{stem}.pt")
        # reduce=frame: float64 sums accumulated row by row in dataset order, divided by the count
        frames = sorted(set(columns["index"].tolist()))
        means, tokens = [], []
        for frame in frames:
            total, count = torch.zeros(WIDTH, dtype=torch.float64), 0
            for row, index in zip(rows, columns["index"].tolist()):
                if index == frame:
                    total, count = total + row.double(), count + 1
            means.append((total / count).float())
            tokens.append(count)
        first_rows = [columns["index"].tolist().index(frame) for frame in frames]
        frame_columns = {column: columns[column][first_rows] for column in ("index", "episode_index", "frame_index")}
        save_file({"residuals": torch.stack(means), **frame_columns, "tokens": torch.tensor(tokens)},
                  expected_dir / f"{stem}-frames.safetensors")
        written = (tmp_path / "frames" / "layer05" / f"{stem}.safetensors").read_bytes()
        assert written == (expected_dir / f"{stem}-frames.safetensors").read_bytes(), name


def test_frame_means_and_max_samples(tmp_path, run_dir, concept_map):
    expected = brute_force(run_dir, concept_map, 5)
    slice_concepts(run_dir, concept_map, tmp_path / "frames", SliceSettings(layers=(5,), reduce="frame"))
    for name, (rows, keys) in expected.items():
        frames = sorted({index for index, _ in keys})
        means = torch.stack([rows[[i for i, k in enumerate(keys) if k[0] == f]].mean(0) for f in frames])
        stored = load_file(tmp_path / "frames" / "layer05" / f"{safe_file_name(name)}.safetensors")
        torch.testing.assert_close(stored["residuals"], means, rtol=0, atol=1e-6)
        assert stored["index"].tolist() == frames

    slice_concepts(run_dir, concept_map, tmp_path / "few", SliceSettings(layers=(5,), max_samples_per_concept=5))
    rows, keys = expected[OPEN]
    keep = [(j * len(keys)) // 5 for j in range(5)]  # documented rule: evenly spaced in dataset order
    stored = load_file(tmp_path / "few" / "layer05" / f"{safe_file_name(OPEN)}.safetensors")
    assert torch.equal(stored["residuals"], rows[keep])

    settings = SliceSettings(layers=(5,), reduce="frame", max_samples_per_concept=3)
    slice_concepts(run_dir, concept_map, tmp_path / "few_frames", settings)
    frames = sorted({index for index, _ in expected[CLOSE][1]})  # 5 frames -> keep 0, 1, 3
    stored = load_file(tmp_path / "few_frames" / "layer05" / f"{CLOSE}.safetensors")
    assert stored["index"].tolist() == [frames[0], frames[1], frames[3]]
    assert stored["tokens"].tolist() == [2, 2, 1]  # episode 3 ("close it") has a one-token span


def test_slicing_is_independent_of_shard_grouping(tmp_path, concept_map):
    for per_shard in (1, 3):
        build_run(tmp_path / f"run{per_shard}", episodes_per_shard=per_shard)
    slice_concepts(tmp_path / "run1", concept_map, tmp_path / "a", SliceSettings(layers=(2,)))
    slice_concepts(tmp_path / "run3", concept_map, tmp_path / "b", SliceSettings(layers=(2,)))
    a = load_file(tmp_path / "a" / "layer02" / f"{CLOSE}.safetensors")
    b = load_file(tmp_path / "b" / "layer02" / f"{CLOSE}.safetensors")
    assert a["index"].tolist() == b["index"].tolist()


def test_errors(tmp_path, run_dir, concept_map):
    out = tmp_path / "out"
    with pytest.raises(ValueError) as err:
        slice_concepts(run_dir, concept_map, out, SliceSettings(layers=(2, 12), token_type="prompt"))
    message = str(err.value)
    assert "the run captured `instructions` tokens, not `prompt`; pass --token-type instructions" in message
    assert "the run has layers [2, 5], not [12]; re-run capture with --layers 12" in message

    other = write_concept_map(tmp_path / "other.json", {OPEN: [segment(7, 0, 3)], CLOSE: [segment(1, 0, 9)]})
    with pytest.raises(ValueError) as err:
        slice_concepts(run_dir, other, out, SliceSettings(layers=(2,)))
    message = str(err.value)
    assert f"concept '{OPEN}' segment 0 needs episode 7 (frames 0-3), which run {run_dir} never captured " \
           "(it holds episodes 0-3); the concept map belongs to another dataset" in message

    beyond = write_concept_map(tmp_path / "beyond.json", {CLOSE: [segment(1, 0, 9)]})
    with pytest.raises(ValueError, match=f"concept '{CLOSE}' segment 0 needs episode 1 frames 5-9, which run"):
        slice_concepts(run_dir, beyond, out, SliceSettings(layers=(2,)))

    shifted = write_concept_map(tmp_path / "shifted.json", {CLOSE: [segment(1, 0, 2, start_index=40, end_index=42)]})
    shifted_message = f"puts episode 1 frame 0 at index 40, but run {run_dir} captured it at index 7"
    with pytest.raises(ValueError, match=shifted_message):
        slice_concepts(run_dir, shifted, out, SliceSettings(layers=(2,)))

    empty = write_concept_map(tmp_path / "empty.json", {OPEN: [segment(0, 0, 1)], CLOSE: []})
    with pytest.raises(ValueError, match=f"concept '{CLOSE}' has no segments; remove it or rebuild the concept map"):
        slice_concepts(run_dir, empty, out, SliceSettings(layers=(2,)))
    assert not out.exists()


def test_safe_file_names():
    assert safe_file_name("open the top drawer of the cabinet") == "open the top drawer of the cabinet"
    assert safe_file_name("../a/b\\c\nd") == "_a_b_c_d"
    assert safe_file_name("...") == "concept"
    assert len(safe_file_name("é" * 300).encode()) <= 200
    names = slice_file_names(["a/b", "a_b", "Up", "up", "x"])
    assert names["x"] == "x"
    assert len({n.casefold() for n in names.values()}) == 5
    assert names["a/b"].startswith("a_b [") and names["Up"].startswith("Up [")


def test_verify_checksums_catches_a_changed_shard(tmp_path, run_dir, concept_map):
    shard = run_dir / "instructions" / "layer02" / "shard-00000.safetensors"
    data = bytearray(shard.read_bytes())
    data[-1] ^= 0xFF
    shard.write_bytes(bytes(data))
    with pytest.raises(ValueError, match="shard-00000.safetensors: CRC-32 is .* re-run capture to rewrite it"):
        slice_concepts(run_dir, concept_map, tmp_path / "checked", SliceSettings(layers=(2,)))  # by default
    assert not (tmp_path / "checked").exists()
    slice_concepts(run_dir, concept_map, tmp_path / "unchecked", SliceSettings(layers=(2,), verify_checksums=False))


def test_a_shard_is_checked_whole_even_where_no_concept_reads_it(tmp_path, run_dir):
    """Damage in rows no concept selects still stops a checked slicing; unchecked, the selected rows are right."""
    concept_map = write_concept_map(tmp_path / "early.json", {OPEN: [segment(0, 0, 1)], CLOSE: [segment(1, 0, 1)]})
    shard = run_dir / "instructions" / "layer02" / "shard-00000.safetensors"  # episodes 0 and 1: episode 1 frame 4 last
    data = bytearray(shard.read_bytes())
    data[-1] ^= 0xFF
    shard.write_bytes(bytes(data))
    with pytest.raises(ValueError, match="shard-00000.safetensors: CRC-32 is [0-9a-f]{8}, expected [0-9a-f]{8}"):
        slice_concepts(run_dir, concept_map, tmp_path / "checked", SliceSettings(layers=(2,)))
    slice_concepts(run_dir, concept_map, tmp_path / "unchecked", SliceSettings(layers=(2,), verify_checksums=False))
    for name, (rows, _) in brute_force(run_dir, concept_map, 2).items():
        assert torch.equal(load_file(tmp_path / "unchecked" / "layer02" / f"{safe_file_name(name)}.safetensors")
                           ["residuals"], rows)


def test_a_run_recorded_without_crc32s_is_checked_by_sha256(tmp_path, run_dir, concept_map):
    """Shard records written before CRC-32s were kept fall back to their sha256."""
    for path in [run_dir / shards.METADATA_FILE, *run_dir.rglob("*.json")]:
        text = path.read_text()
        if '"crc32"' in text:
            payload = json.loads(text)
            for record in payload.get("shards", [payload]):
                record.pop("crc32", None)
            path.write_text(json.dumps(payload))
    assert shards.read_run_metadata(run_dir).shards[0].crc32 is None
    shard = run_dir / "instructions" / "layer02" / "shard-00000.safetensors"
    data = bytearray(shard.read_bytes())
    data[-1] ^= 0xFF
    shard.write_bytes(bytes(data))
    with pytest.raises(ValueError, match="shard-00000.safetensors: sha256 is [0-9a-f]{64}, expected [0-9a-f]{64}"):
        slice_concepts(run_dir, concept_map, tmp_path / "checked", SliceSettings(layers=(2,)))


def test_a_shard_with_a_damaged_header_is_reported_by_its_checksum(tmp_path, run_dir, concept_map):
    """The checksums are computed beside the slicing: a shard that fails to open is still named as changed."""
    shard = run_dir / "instructions" / "layer02" / "shard-00000.safetensors"
    data = bytearray(shard.read_bytes())
    data[10:20] = b"#" * 10  # inside the JSON header
    shard.write_bytes(bytes(data))
    with pytest.raises(ValueError, match="shard-00000.safetensors: CRC-32 is .* re-run capture to rewrite it"):
        slice_concepts(run_dir, concept_map, tmp_path / "checked", SliceSettings(layers=(2,)))
    assert not (tmp_path / "checked").exists()
    with pytest.raises(ValueError, match="shard-00000.safetensors.*(not a readable safetensors|header)"):
        slice_concepts(run_dir, concept_map, tmp_path / "unchecked", SliceSettings(layers=(2,), verify_checksums=False))


def test_slice_command(tmp_path, run_dir, concept_map):
    from typer.testing import CliRunner

    from latent_steering_cli.capture import app

    args = ["slice", "--run-dir", str(run_dir), "--concept-map-path", str(concept_map),
            "--output-dir", str(tmp_path / "cli"), "--token-type", "instructions", "--layers", "2,5",
            "--device", "cpu", "--reduce", "frame", "--max-samples-per-concept", "4"]
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 0, result.output
    slice_concepts(run_dir, concept_map, tmp_path / "lib",
                   SliceSettings(layers=(2, 5), reduce="frame", max_samples_per_concept=4))
    for layer in ("layer02", "layer05"):
        cli = torch.load(tmp_path / "cli" / layer / f"{CLOSE}.pt", weights_only=True)
        assert torch.equal(cli, torch.load(tmp_path / "lib" / layer / f"{CLOSE}.pt", weights_only=True))

    result = CliRunner().invoke(app, [*args[:-6], "--layers", "12"])
    assert result.exit_code == 1
    assert "re-run capture with --layers 12" in result.output


def test_held_out_episodes_never_reach_the_slices(tmp_path, run_dir, concept_map):
    """Slices with episodes 2 and 3 held out equal the brute force over a map without them; none of their rows."""
    held_out = (2, 3)
    out = tmp_path / "slices"
    written = slice_concepts(run_dir, concept_map, out, SliceSettings(layers=(2,), holdout_episodes=held_out))
    payload = json.loads(concept_map.read_text())
    payload["concepts"] = {name: [s for s in segs if s["episode_index"] not in held_out]
                           for name, segs in payload["concepts"].items()}
    reduced = write_concept_map(tmp_path / "train_map.json", payload["concepts"])
    expected = brute_force(run_dir, reduced, 2)
    index = json.loads(written[2].read_text())
    assert index["settings"]["holdout_episodes"] == list(held_out)
    for name, (rows, _keys) in expected.items():
        copy = load_file(out / "layer02" / index["concepts"][name]["safetensors"])
        assert torch.equal(copy["residuals"], rows)
        assert not set(copy["episode_index"].tolist()) & set(held_out)
    # holding nothing out reproduces the slices of a run without a split, byte for byte
    plain, empty = tmp_path / "plain", tmp_path / "empty"
    slice_concepts(run_dir, concept_map, plain, SliceSettings(layers=(2,)))
    slice_concepts(run_dir, concept_map, empty, SliceSettings(layers=(2,), holdout_episodes=()))
    for name in (OPEN, CLOSE):
        stem = safe_file_name(name)
        for suffix in (".pt", ".safetensors"):
            assert (plain / "layer02" / f"{stem}{suffix}").read_bytes() == (empty / "layer02" / f"{stem}{suffix}").read_bytes()


def test_concept_map_of_another_dataset_is_refused(tmp_path, concept_map):
    """Same episode layout, other dataset: the map's repo_id or dataset content must be the run's."""
    from helpers_dataset import contrast_episodes, write_dataset

    from steering_core.data.dataset import dataset_fingerprint

    episodes = contrast_episodes()
    ours, theirs = tmp_path / "ours", tmp_path / "theirs"
    write_dataset(ours, episodes)
    write_dataset(theirs, [(task, states + 1) for task, states in episodes])
    run_dir = tmp_path / "run"
    build_run(run_dir, sources={"repo_id": "test", "dataset_fingerprint": dataset_fingerprint(ours)})
    out = tmp_path / "out"

    other_repo = json.loads(concept_map.read_text()) | {"repo_id": "libero_other"}
    (tmp_path / "other_repo.json").write_text(json.dumps(other_repo))
    with pytest.raises(ValueError, match=r"other_repo.json: the concept map is of dataset 'libero_other', but run .* "
                                         r"captured 'test'"):
        slice_concepts(run_dir, tmp_path / "other_repo.json", out, SliceSettings(layers=(2,)))

    other_content = json.loads(concept_map.read_text()) | {"lerobot_root": str(theirs)}
    (tmp_path / "other_content.json").write_text(json.dumps(other_content))
    with pytest.raises(ValueError, match=r"other_content.json: its dataset .*theirs has fingerprint .*, run .* "
                                         r"captured a dataset with fingerprint"):
        slice_concepts(run_dir, tmp_path / "other_content.json", out, SliceSettings(layers=(2,)))
    assert not out.exists()

    same = json.loads(concept_map.read_text()) | {"lerobot_root": str(ours)}
    (tmp_path / "same.json").write_text(json.dumps(same))
    slice_concepts(run_dir, tmp_path / "same.json", out, SliceSettings(layers=(2,)))


def test_a_second_slice_waits_for_the_layer_another_process_writes_then_keeps_it(
        tmp_path, run_dir, concept_map, monkeypatch):
    import shutil

    from steering_core.capture import slicing

    reference = tmp_path / "reference"
    slice_concepts(run_dir, concept_map, reference, SliceSettings(layers=(2,)))
    out = tmp_path / "slices"
    reads = []
    real_read = slicing._write_slices
    monkeypatch.setattr(slicing, "_write_slices", lambda *a, **k: reads.append(1) or real_read(*a, **k))
    holder = hold_output_lock(out / "layer02")
    worker, outcome = start_waiting(lambda: slice_concepts(run_dir, concept_map, out, SliceSettings(layers=(2,))))
    assert not (out / "layer02").exists()  # waiting, nothing computed
    shutil.copytree(reference / "layer02", out / "layer02")  # the other process finishes the layer
    holder.communicate("done\n", timeout=30)
    worker.join(timeout=60)
    assert outcome["result"] == {2: out / "layer02" / "index.json"} and reads == []  # kept, not recomputed
    assert sorted(p.name for p in (out / "layer02").iterdir()) == sorted(p.name for p in (reference / "layer02").iterdir())

    # a finished layer of other inputs is not kept: another reduction recomputes, under the same lock
    slice_concepts(run_dir, concept_map, out, SliceSettings(layers=(2,), reduce="frame"))
    assert reads == [1] and json.loads((out / "layer02" / "index.json").read_text())["settings"]["reduce"] == "frame"
    (out / "layer02" / "open the top_drawer.pt").unlink()  # an incomplete layer is not kept either
    slice_concepts(run_dir, concept_map, out, SliceSettings(layers=(2,), reduce="frame"))
    assert reads == [1, 1] and (out / "layer02" / "open the top_drawer.pt").is_file()
