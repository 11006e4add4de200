"""Capture: stored rows equal direct model calls, token selection, resume, split runs, errors, CLI."""

from __future__ import annotations

import threading

import pytest
import sentencepiece
import torch
from helpers_capture import EPISODES, make_lerobot_dataset
from safetensors.torch import load_file

from steering_core.capture import CaptureSettings, capture, loop, shards
from steering_core.capture.frames import worker_start_method
from steering_core.capture.run_identity import checkpoint_fingerprint
from steering_core.capture.settings import select_tokens
from steering_core.pi05 import PromptFormat, PromptTokenizer, libero_camera_slots, quantile_normalize, read_norm_stats
from steering_core.pi05.model import Pi05Prefix
from steering_core.pi05.spec import ModelSpec
from steering_core.synthetic.pi05 import tiny_arch, write_pi05_checkpoint
from steering_core.synthetic.tokenizer import write_tokenizer

ARCH = tiny_arch()
LANGUAGE_START = 3 * ARCH.tokens_per_image  # three camera slots precede the language tokens
REPO_ID = "local/capture"


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    """A tiny checkpoint, tokenizer and dataset shared by every test: (checkpoint, tokenizer, dataset)."""
    root = tmp_path_factory.mktemp("inputs")
    checkpoint = write_pi05_checkpoint(root / "checkpoint", ARCH)
    tokenizer = write_tokenizer(root / "tokenizer.model")
    dataset = make_lerobot_dataset(root / "dataset")
    return checkpoint, tokenizer, dataset


MODEL_FIELDS = {"checkpoint_path": "checkpoint", "tokenizer_path": "tokenizer", "arch": "arch",
                "prompt_format": "prompt_format"}  # settings_for's override names -> ModelSpec fields


def settings_for(inputs, **overrides) -> CaptureSettings:
    checkpoint, tokenizer, _ = inputs
    model = {"checkpoint": checkpoint, "tokenizer": tokenizer, "arch": ARCH}
    model |= {MODEL_FIELDS[name]: overrides.pop(name) for name in list(overrides) if name in MODEL_FIELDS}
    fields = dict(layers=(1, 3), batch_size=2, device="cpu", num_workers=0)
    return CaptureSettings(**(fields | overrides), model=ModelSpec(**model))


@pytest.fixture(scope="module")
def full_run(inputs, tmp_path_factory):
    """An uninterrupted instruction-token capture every other test compares with."""
    run_dir = tmp_path_factory.mktemp("full") / "run"
    capture(inputs[2], REPO_ID, run_dir, settings_for(inputs, num_workers=1))
    return run_dir


def load_layer(run_dir, layer, token_type="instructions"):
    """Return every shard of a layer concatenated: residuals and columns, ordered by (index, position)."""
    parts = [load_file(p) for p in sorted((run_dir / token_type / f"layer{layer:02d}").glob("*.safetensors"))]
    return {key: torch.cat([p[key] for p in parts]) for key in parts[0]}


def direct_frames(dataset_root):
    """Every frame read straight from lerobot, in index order, preprocessed for the model."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    frames = LeRobotDataset(REPO_ID, root=dataset_root)
    items = [frames[i] for i in range(len(frames))]
    image = torch.stack([item["image"] for item in items])
    wrist = torch.stack([item["wrist_image"] for item in items])
    images, masks = libero_camera_slots(image, wrist, ARCH.image_size)
    return items, images, masks


def test_rows_equal_direct_model_call(inputs, full_run):
    checkpoint, tokenizer_path, dataset = inputs
    items, images, masks = direct_frames(dataset)
    tokenizer = PromptTokenizer(tokenizer_path)
    pieces = sentencepiece.SentencePieceProcessor(model_file=str(tokenizer_path))
    prompts = [tokenizer.tokenize(item["task"]) for item in items]
    tokens = torch.stack([torch.from_numpy(p.ids) for p in prompts])
    token_mask = torch.stack([torch.from_numpy(p.mask) for p in prompts])
    model = Pi05Prefix.from_checkpoint(checkpoint, ARCH, device="cpu")
    # the full computation (every camera, no trimming), all frames in one batch
    direct = model.residuals(images, masks, tokens, token_mask, [1, 3], skip_masked_images=False, trim_padding=False)

    expected_rows = {1: [], 3: []}
    expected_columns = []
    for frame, (item, prompt) in enumerate(zip(items, prompts)):
        start, end = prompt.instruction
        assert end - start == len(pieces.encode(item["task"])) > 0
        for language_index in range(start, end):
            position = LANGUAGE_START + language_index
            expected_columns.append((int(item["index"]), int(item["episode_index"]), int(item["frame_index"]),
                                     position, int(prompt.ids[language_index])))
            for layer in (1, 3):
                expected_rows[layer].append(direct[layer][frame, position])
    for layer in (1, 3):
        stored = load_layer(full_run, layer)
        columns = list(zip(*(stored[name].tolist() for name in shards.ROW_COLUMNS)))
        assert columns == expected_columns
        torch.testing.assert_close(stored["residuals"], torch.stack(expected_rows[layer]), rtol=1e-5, atol=1e-5)

    metadata = shards.read_run_metadata(full_run)
    assert metadata.episodes == (0, 1, 2, 3)
    assert [r.key for r in metadata.layer_shards(3)] == ["00000", "00001", "00002", "00003"]
    open_task = metadata.tasks["open the top drawer"]
    prompt = tokenizer.tokenize("open the top drawer")
    assert open_task["token_ids"] == prompt.ids[slice(*prompt.instruction)].tolist()
    assert open_task["token_positions"] == [LANGUAGE_START + i for i in range(*prompt.instruction)]
    assert open_task["varies_per_frame"] is False
    assert metadata.run.sources["dataset_root"] == str(dataset.resolve())
    assert metadata.run.inputs["compute_dtype"] == "float32"


@pytest.mark.parametrize("token_type", ["prompt", "last"])
def test_token_types_select_their_positions(inputs, full_run, tmp_path, token_type):
    run_dir = tmp_path / token_type
    capture(inputs[2], REPO_ID, run_dir, settings_for(inputs, token_type=token_type))
    stored, instructions = load_layer(run_dir, 3, token_type), load_layer(full_run, 3)
    tokenizer = PromptTokenizer(inputs[1])
    expected = []
    for frame, (_frames, task) in enumerate(t for t in EPISODES for _ in range(t[0])):
        prompt = tokenizer.tokenize(task)
        chosen = range(prompt.n_valid) if token_type == "prompt" else [prompt.n_valid - 1]
        expected += [(frame, LANGUAGE_START + i, int(prompt.ids[i])) for i in chosen]
    assert list(zip(stored["index"].tolist(), stored["token_position"].tolist(), stored["token_id"].tolist())) \
        == expected
    if token_type == "prompt":  # same batches, same model: the instruction rows again
        keys = list(zip(stored["index"].tolist(), stored["token_position"].tolist()))
        wanted = [keys.index(k) for k in zip(instructions["index"].tolist(), instructions["token_position"].tolist())]
        # layer 1 is computed for every token either way: bit-identical
        assert torch.equal(load_layer(run_dir, 1, token_type)["residuals"][wanted], load_layer(full_run, 1)["residuals"])
        # the deepest layer computes only the selected rows' queries, and another selection is another
        # product shape: equal up to float32 rounding
        difference = (stored["residuals"][wanted] - instructions["residuals"]).abs().max()
        assert difference <= 1e-6 * instructions["residuals"].abs().max()
    else:
        newline = sentencepiece.SentencePieceProcessor(model_file=str(inputs[1])).piece_to_id("\n")
        assert set(stored["token_id"].tolist()) == {newline}  # the libero prompt ends with "\n"


def test_select_tokens(inputs):
    prompt = PromptTokenizer(inputs[1]).tokenize("close the top drawer")
    assert select_tokens(prompt, "instructions").tolist() == list(range(*prompt.instruction))
    assert select_tokens(prompt, "prompt").tolist() == list(range(prompt.n_valid))
    assert select_tokens(prompt, "last").tolist() == [prompt.n_valid - 1]
    assert prompt.instruction[0] == 1 and prompt.instruction[1] == prompt.n_valid - 1  # BOS, words, "\n"


def test_kill_and_resume_is_byte_identical(inputs, full_run, tmp_path):
    run_dir = tmp_path / "run"
    calls = []

    def stop_after_three_batches(done, total):
        calls.append((done, total))
        if len(calls) == 3:  # episode 0 (3 frames: 2 batches) and episode 1 (1 batch) are written
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        capture(inputs[2], REPO_ID, run_dir, settings_for(inputs), progress=stop_after_three_batches)
    assert calls == [(2, 11), (3, 11), (5, 11)]
    assert not (run_dir / "metadata.json").exists()
    assert sorted(p.name for p in (run_dir / "instructions" / "layer01").iterdir()) == [
        "shard-00000.json", "shard-00000.safetensors", "shard-00001.json", "shard-00001.safetensors"]

    # a damaged shard is redone, complete ones are skipped
    damaged = run_dir / "instructions" / "layer03" / "shard-00001.safetensors"
    damaged.write_bytes(damaged.read_bytes()[:-4])
    result = capture(inputs[2], REPO_ID, run_dir, settings_for(inputs))
    assert result.skipped == ("00000",) and result.written == ("00001", "00002", "00003")
    assert result.frames == 8
    for layer in (1, 3):
        for name in ("00000", "00001", "00002", "00003"):
            relative = f"instructions/layer{layer:02d}/shard-{name}.safetensors"
            assert (run_dir / relative).read_bytes() == (full_run / relative).read_bytes()
    assert shards.read_run_metadata(run_dir).run_fingerprint == shards.read_run_metadata(full_run).run_fingerprint

    again = capture(inputs[2], REPO_ID, run_dir, settings_for(inputs))
    assert again.written == () and again.frames == 0

    with pytest.raises(ValueError, match=r"other settings \(differs in layers\); choose a new output folder"):
        capture(inputs[2], REPO_ID, run_dir, settings_for(inputs, layers=(2,)))


def test_a_grown_dataset_keeps_existing_shards(inputs, full_run, tmp_path):
    # the same generator writes the first three episodes identically, then stops
    smaller = make_lerobot_dataset(tmp_path / "smaller", episodes=EPISODES[:3])
    run_dir = tmp_path / "run"
    first = capture(smaller, REPO_ID, run_dir, settings_for(inputs))
    assert first.written == ("00000", "00001", "00002")
    stamps = {p: p.stat().st_mtime_ns for p in run_dir.rglob("*.safetensors")}
    grown = capture(inputs[2], REPO_ID, run_dir, settings_for(inputs))
    assert grown.skipped == ("00000", "00001", "00002") and grown.written == ("00003",)
    assert all(p.stat().st_mtime_ns == stamp for p, stamp in stamps.items())
    metadata = shards.read_run_metadata(run_dir)
    assert metadata.run_fingerprint == shards.read_run_metadata(full_run).run_fingerprint
    assert metadata.run.sources["dataset_root"] == str(inputs[2].resolve())


def test_split_run_equals_full_run(inputs, full_run, tmp_path):
    run_dir = tmp_path / "split"
    first = capture(inputs[2], REPO_ID, run_dir, settings_for(inputs, episodes_per_shard=2), episodes=[2, 3])
    assert first.metadata is None and first.written == ("00001",)
    capture(inputs[2], REPO_ID, run_dir, settings_for(inputs, episodes_per_shard=2), episodes=[0, 1])
    shards.write_run_metadata(run_dir)
    metadata = shards.read_run_metadata(run_dir)
    assert [r.episodes for r in metadata.layer_shards(1)] == [(0, 1), (2, 3)]
    split, full = load_layer(run_dir, 1), load_layer(full_run, 1)
    assert split.keys() == full.keys()
    for name in split:
        assert torch.equal(split[name], full[name]), name

    with pytest.raises(ValueError, match=r"episodes \[1\] split shard group 00000 \(episodes \[0, 1\]\); pass whole"):
        capture(inputs[2], REPO_ID, run_dir, settings_for(inputs, episodes_per_shard=2), episodes=[1])
    with pytest.raises(ValueError, match=r"episodes \[9\] are not in the dataset"):
        capture(inputs[2], REPO_ID, run_dir, settings_for(inputs, episodes_per_shard=2), episodes=[9])


def test_workers_in_a_threaded_process_equal_the_plain_run(inputs, full_run, tmp_path):
    """Inside a Prefect flow other threads run; workers start from a forkserver and give the same rows."""
    assert worker_start_method(0) is None and worker_start_method(1) == "forkserver"
    stop = threading.Event()
    busy = threading.Thread(target=stop.wait, daemon=True)
    busy.start()
    try:
        capture(inputs[2], REPO_ID, tmp_path / "run", settings_for(inputs, num_workers=2))
    finally:
        stop.set()
        busy.join()
    ours, full = load_layer(tmp_path / "run", 3), load_layer(full_run, 3)
    assert all(torch.equal(ours[name], full[name]) for name in full)


def test_discrete_state_prompt(inputs, tmp_path):
    checkpoint, tokenizer_path, dataset = inputs
    settings = settings_for(inputs, token_type="prompt", prompt_format="discrete_state", layers=(0,))
    result = capture(dataset, REPO_ID, tmp_path / "run", settings, episodes=[1])
    assert result.written == ("00001",)
    stored = load_layer(tmp_path / "run", 0, "prompt")

    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    frames = LeRobotDataset(REPO_ID, root=dataset, episodes=[1])
    tokenizer = PromptTokenizer(tokenizer_path, prompt_format=PromptFormat.DISCRETE_STATE)
    stats = read_norm_stats(checkpoint)["state"]
    expected = []
    for item in (frames[i] for i in range(len(frames))):
        prompt = tokenizer.tokenize(item["task"], quantile_normalize(item["state"].numpy(), stats))
        expected += prompt.ids[: prompt.n_valid].tolist()
    assert stored["token_id"].tolist() == expected
    record = shards.read_shard_record(tmp_path / "run" / "prompt" / "layer00" / "shard-00001.json")
    assert record.tasks["close the top drawer"]["varies_per_frame"] is True  # the state tokens differ


def test_capture_errors(inputs, tmp_path):
    checkpoint, tokenizer, dataset = inputs
    run_dir = tmp_path / "run"
    with pytest.raises(FileNotFoundError, match="tokenizer not found"):
        capture(dataset, REPO_ID, run_dir, settings_for(inputs, tokenizer_path=tmp_path / "none.model"))
    with pytest.raises(FileNotFoundError, match="pi0.5 checkpoint not found"):
        capture(dataset, REPO_ID, run_dir, settings_for(inputs, checkpoint_path=tmp_path / "none"))
    out_of_range = r"layers \[4, 7\] out of range: the language model has 4 decoder layers \(0..3\)"
    with pytest.raises(ValueError, match=out_of_range):
        capture(dataset, REPO_ID, run_dir, settings_for(inputs, layers=(1, 4, 7)))
    with pytest.raises(ValueError, match="needs the quantile-normalised state: drop --skip-norm-stats"):
        capture(dataset, REPO_ID, run_dir,
                settings_for(inputs, prompt_format="discrete_state", skip_norm_stats=True))
    with pytest.raises(FileNotFoundError, match="LeRobot dataset folder not found"):
        capture(tmp_path / "no_dataset", REPO_ID, run_dir, settings_for(inputs))
    one_camera = make_lerobot_dataset(tmp_path / "one_camera", episodes=[(1, "open the top drawer")],
                                      cameras=("image",))
    with pytest.raises(ValueError, match=r"feature `wrist_image` is missing, expected a camera \(image or video\)"):
        capture(one_camera, REPO_ID, run_dir, settings_for(inputs))
    wider = ARCH.model_copy(update={"width": 32})
    with pytest.raises(ValueError, match=r"prefix tensors .* are missing or do not match"):
        capture(dataset, REPO_ID, run_dir, settings_for(inputs, arch=wider))
    assert not run_dir.exists()


def test_capture_command(inputs, tmp_path):
    from typer.testing import CliRunner

    from latent_steering_cli.capture import app

    checkpoint, tokenizer, dataset = inputs
    arch_file = tmp_path / "arch.json"
    arch_file.write_text(ARCH.model_dump_json())
    args = ["capture", "--checkpoint-path", str(checkpoint), "--output-dir", str(tmp_path / "run"),
            "--layers", "0,2", "--batch-size", "4", "--capture-instructions", "--skip-norm-stats", "--device", "cpu",
            "--lerobot-root", str(dataset), "--repo-id", REPO_ID, "--tokenizer-path", str(tokenizer),
            "--storage-dtype", "bfloat16", "--num-workers", "0", "--arch-file", str(arch_file)]
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 0, result.output
    metadata = shards.read_run_metadata(tmp_path / "run")
    assert metadata.run.layers == (0, 2) and metadata.run.storage_dtype == "bfloat16"
    assert metadata.run.token_type == "instructions"

    result = CliRunner().invoke(app, [*args, "--layers", "9", "--output-dir", str(tmp_path / "other")])
    assert result.exit_code == 1
    assert "layers [9] out of range" in result.output


def test_seed_command_with_max_samples_per_layer(inputs, full_run, tmp_path):
    """The seed's spellings (`--layers 1 3`, underscores) and its cap: the first episodes until 4 frames (3 + 2)."""
    from typer.testing import CliRunner

    from latent_steering_cli import app

    checkpoint, tokenizer, dataset = inputs
    arch_file = tmp_path / "arch.json"
    arch_file.write_text(ARCH.model_dump_json())
    result = CliRunner().invoke(app, [
        "capture", "--checkpoint_path", str(checkpoint), "--output_dir", str(tmp_path / "run"), "--layers", "1", "3",
        "--batch_size", "2", "--capture_instructions", "--skip_norm_stats", "--device", "cpu", "--lerobot_root",
        str(dataset), "--repo_id", REPO_ID, "--tokenizer_path", str(tokenizer), "--num_workers", "0",
        "--arch_file", str(arch_file), "--max_samples_per_layer", "4"])
    assert result.exit_code == 0, result.output
    metadata = shards.read_run_metadata(tmp_path / "run")
    assert metadata.episodes == (0, 1) and metadata.run.layers == (1, 3)
    for layer in (1, 3):
        paths = sorted((tmp_path / "run" / "instructions" / f"layer{layer:02d}").glob("*.safetensors"))
        assert len(paths) == 2  # one shard per episode
        for path in paths:
            ours, full = load_file(path), load_file(full_run / "instructions" / f"layer{layer:02d}" / path.name)
            assert all(torch.equal(ours[k], full[k]) for k in full)


def test_checkpoint_fingerprint_tells_same_layout_checkpoints_apart(inputs, tmp_path):
    model_file = inputs[0] / "model.safetensors"
    other = write_pi05_checkpoint(tmp_path / "other", ARCH, seed=1) / "model.safetensors"
    same = write_pi05_checkpoint(tmp_path / "same", ARCH, seed=0) / "model.safetensors"
    assert other.stat().st_size == model_file.stat().st_size
    assert checkpoint_fingerprint(same) == checkpoint_fingerprint(model_file)
    assert checkpoint_fingerprint(other) != checkpoint_fingerprint(model_file)


def rewrite_episode(dataset_root, episode, change):
    """Rewrite the data parquet rows of one episode in place: `change(row)` edits each row dict."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    for path in sorted((dataset_root / "data").rglob("*.parquet")):
        table = pq.read_table(path)
        rows = table.to_pylist()
        for row in rows:
            if row["episode_index"] == episode:
                change(row)
        pq.write_table(pa.Table.from_pylist(rows, schema=table.schema), path)


def swap_cameras(row):
    row["image"], row["wrist_image"] = row["wrist_image"], row["image"]


def negate_state(row):
    row["state"] = [-v for v in row["state"]]


def negate_actions(row):
    row["actions"] = [-v for v in row["actions"]]


@pytest.mark.parametrize(("change", "recomputed"), [
    (swap_cameras, ("00001",)),   # the frames: what the issue found reused (re-converted with another orientation)
    (negate_state, ("00001",)),
    (negate_actions, ()),          # capture never reads actions
])
def test_resume_recomputes_exactly_the_groups_whose_inputs_changed(inputs, full_run, tmp_path, change, recomputed):
    import shutil

    dataset = tmp_path / "dataset"
    shutil.copytree(inputs[2], dataset)
    run_dir = tmp_path / "run"
    shutil.copytree(full_run, run_dir)
    rewrite_episode(dataset, 1, change)
    result = capture(dataset, REPO_ID, run_dir, settings_for(inputs))
    assert result.written == recomputed
    assert result.skipped == tuple(k for k in ("00000", "00001", "00002", "00003") if k not in recomputed)
    if change is swap_cameras:  # the rewritten rows are those of a fresh capture of the changed frames
        fresh = tmp_path / "fresh"
        capture(dataset, REPO_ID, fresh, settings_for(inputs))
        relative = "instructions/layer03/shard-00001.safetensors"
        assert (run_dir / relative).read_bytes() == (fresh / relative).read_bytes()
        assert (run_dir / relative).read_bytes() != (full_run / relative).read_bytes()


def test_an_output_path_that_is_a_file_fails_before_the_model_loads(inputs, tmp_path, monkeypatch):
    monkeypatch.setattr(Pi05Prefix, "from_checkpoint", lambda *a, **k: pytest.fail("the model was loaded"))
    taken = tmp_path / "run"
    taken.write_text("a file where the run folder goes")
    with pytest.raises(ValueError, match=f"{taken}: is a file; expected a folder"):
        capture(inputs[2], REPO_ID, taken, settings_for(inputs))
    with pytest.raises(ValueError, match=rf"{taken}: is a file \(a parent of the run folder"):
        capture(inputs[2], REPO_ID, taken / "inner", settings_for(inputs))


@pytest.mark.parametrize("content", [b"plain text, not tensors\n", b"\x80\x04\x95 a pickle renamed"])
def test_capture_command_refuses_a_checkpoint_that_is_not_safetensors_in_one_line(inputs, tmp_path, content):
    from typer.testing import CliRunner

    from latent_steering_cli.capture import app

    _, tokenizer, dataset = inputs
    bad = tmp_path / "model.safetensors"
    bad.write_bytes(content)
    arch_file = tmp_path / "arch.json"
    arch_file.write_text(ARCH.model_dump_json())
    result = CliRunner().invoke(app, [
        "capture", "--checkpoint-path", str(bad), "--output-dir", str(tmp_path / "run"), "--layers", "1",
        "--capture-instructions", "--skip-norm-stats", "--device", "cpu", "--lerobot-root", str(dataset),
        "--repo-id", REPO_ID, "--tokenizer-path", str(tokenizer), "--num-workers", "0", "--arch-file", str(arch_file)])
    assert result.exit_code == 1, result.output
    assert f"{bad}: not a safetensors file" in result.output
    assert "Traceback" not in result.output
    assert not (tmp_path / "run").exists()


def test_non_finite_residuals_stop_capture_naming_episode_and_layer(inputs, tmp_path):
    import shutil

    from safetensors.torch import save_file

    checkpoint = tmp_path / "checkpoint"
    shutil.copytree(inputs[0], checkpoint)
    tensors = load_file(checkpoint / "model.safetensors")
    name = "paligemma_with_expert.paligemma.model.language_model.layers.2.mlp.down_proj.weight"
    tensors[name][0] = 3e38  # finite (the checkpoint passes) but overflows layer 2's output: layer 3 (captured) is
    # poisoned, layer 1 is not
    save_file(tensors, checkpoint / "model.safetensors")
    run_dir = tmp_path / "run"
    with pytest.raises(ValueError, match=r"non-finite residuals \(NaN or Inf\) at layer 3 in episode 0 "
                                         r"\(frame 0\)"):
        capture(inputs[2], REPO_ID, run_dir, settings_for(inputs, checkpoint_path=checkpoint))
    assert not list(run_dir.rglob("*.safetensors"))  # nothing written for the poisoned rows


def test_a_second_capture_waits_for_groups_another_process_is_capturing(inputs, full_run, tmp_path):
    """Another process holds shard group 1 and finishes it; this capture waits, then skips it."""
    import shutil
    import subprocess
    import sys

    run_dir = tmp_path / "run"
    holder = subprocess.Popen(
        [sys.executable, "-c", "import sys; from steering_core.remote.locks import group_locks\n"
         f"with group_locks({str(run_dir)!r}, [1]):\n    print('locked', flush=True); sys.stdin.readline()"],
        stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    assert holder.stdout.readline().strip() == "locked"
    outcome = {}
    worker = threading.Thread(target=lambda: outcome.update(
        result=capture(inputs[2], REPO_ID, run_dir, settings_for(inputs), episodes=[1, 2])))
    worker.start()
    worker.join(timeout=5)
    assert worker.is_alive() and not list(run_dir.rglob("*.safetensors"))  # waiting, nothing computed
    for layer in (1, 3):  # the other process finishes group 1
        for suffix in ("safetensors", "json"):
            relative = f"instructions/layer{layer:02d}/shard-00001.{suffix}"
            (run_dir / relative).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy(full_run / relative, run_dir / relative)
    holder.communicate("done\n", timeout=30)
    worker.join(timeout=300)
    assert outcome["result"].skipped == ("00001",) and outcome["result"].written == ("00002",)


def test_cuda_out_of_memory_halves_the_batch_and_records_it(inputs, full_run, tmp_path, monkeypatch):
    real = loop.selected_residuals  # what capture calls
    sizes = []

    def small_memory(model, images, masks, tokens, *args, **kwargs):
        sizes.append(len(tokens))
        if len(tokens) > 1:  # a GPU that fits one frame per pass
            raise torch.cuda.OutOfMemoryError("CUDA out of memory (simulated)")
        return real(model, images, masks, tokens, *args, **kwargs)

    monkeypatch.setattr(loop, "selected_residuals", small_memory)
    result = capture(inputs[2], REPO_ID, tmp_path / "run", settings_for(inputs, batch_size=2))
    assert result.reduced_batch_size == 1
    assert sizes[:3] == [2, 1, 1] and set(sizes[3:]) == {1}  # halved once, then kept for the rest of the run
    ours, full = load_layer(tmp_path / "run", 3), load_layer(full_run, 3)
    for name in full:
        assert torch.allclose(ours[name].double(), full[name].double(), atol=1e-5), name


def test_out_of_memory_at_one_frame_is_raised(inputs, tmp_path, monkeypatch):
    def no_memory(*args, **kwargs):
        raise torch.cuda.OutOfMemoryError("CUDA out of memory (simulated)")

    monkeypatch.setattr(loop, "selected_residuals", no_memory)
    with pytest.raises(torch.cuda.OutOfMemoryError):
        capture(inputs[2], REPO_ID, tmp_path / "run", settings_for(inputs, batch_size=2), episodes=[1])
