"""Capture of the action token types: decision rows and adaRMS conditioning per denoising step.

Rows are compared with the independent float64 reference of the expert and the sampler
(`reference_policy.reference_actions`, which records the same quantities), fed with noise drawn here
from the documented per-frame seed; resume, slicing, the CLI and bad settings are checked on the same run.
"""

from __future__ import annotations

import json

import pytest
import torch
from helpers_capture import EPISODES
from reference_policy import reference_actions
from test_capture import ARCH, REPO_ID, direct_frames, inputs, load_layer, settings_for  # noqa: F401 (fixture)

from steering_core.capture import capture, shards
from steering_core.capture.slicing import SliceSettings, slice_concepts
from steering_core.pi05 import PromptTokenizer
from steering_core.storage.fileio import sha256_file
from steering_core.synthetic.pi05 import tiny_expert_arch

STEPS, SEED, HORIZON = 3, 7, 10
EXPERT = tiny_expert_arch(ARCH)  # what write_pi05_checkpoint writes beside ARCH
EXPERT_DEPTH = EXPERT.depth
LAYERS = (0, EXPERT_DEPTH - 1)
FRAMES = sum(frames for frames, _ in EPISODES)


def action_settings(inputs, token_type="decision", **overrides):
    fields = dict(token_type=token_type, layers=LAYERS, num_steps=STEPS, noise_seed=SEED)
    return settings_for(inputs, **(fields | overrides))


@pytest.fixture(scope="module")
def decision_run(inputs, tmp_path_factory):
    run_dir = tmp_path_factory.mktemp("decision") / "run"
    capture(inputs[2], REPO_ID, run_dir, action_settings(inputs))
    return run_dir


@pytest.fixture(scope="module")
def reference(inputs):
    """The float64 reference's recorded decision rows and conditioning for every frame, with the seeded noise."""
    checkpoint, tokenizer_path, dataset = inputs
    items, images, masks = direct_frames(dataset)
    tokenizer = PromptTokenizer(tokenizer_path)
    prompts = [tokenizer.tokenize(item["task"]) for item in items]
    tokens = torch.stack([torch.from_numpy(p.ids) for p in prompts])
    token_mask = torch.stack([torch.from_numpy(p.mask) for p in prompts])
    # each frame's noise: its own generator seeded with noise_seed * 2**32 + its global index
    noise = torch.stack([torch.randn(HORIZON, EXPERT.action_dim,
                                     generator=torch.Generator().manual_seed(SEED * 2**32 + i))
                         for i in range(FRAMES)])
    record = {}
    reference_actions(checkpoint / "model.safetensors", ARCH, images, masks, tokens, token_mask, noise,
                      num_steps=STEPS, record=record)
    return items, record


def test_decision_rows_equal_the_float64_reference(decision_run, reference):
    items, record = reference
    for layer in LAYERS:
        stored = load_layer(decision_run, layer, "decision")
        assert stored["residuals"].shape == (FRAMES * STEPS, EXPERT.width)
        assert stored["index"].tolist() == [i for i in range(FRAMES) for _ in range(STEPS)]
        assert stored["step"].tolist() == list(range(STEPS)) * FRAMES
        assert stored["episode_index"].tolist() == [int(item["episode_index"]) for item in items for _ in range(STEPS)]
        assert set(stored["token_position"].tolist()) == {HORIZON - 1} and set(stored["token_id"].tolist()) == {-1}
        expected = torch.stack([record["decision", b, s, layer] for b in range(FRAMES) for s in range(STEPS)])
        torch.testing.assert_close(stored["residuals"].double(), expected, rtol=1e-4, atol=1e-4)
    # different layers and steps hold different rows (the hooks do not all see the same tensor)
    first, last = (load_layer(decision_run, layer, "decision")["residuals"] for layer in LAYERS)
    assert not torch.equal(first, last) and not torch.equal(first[0], first[1])
    metadata = shards.read_run_metadata(decision_run)
    assert metadata.run.width == EXPERT.width and metadata.run.token_type == "decision"
    assert metadata.run.inputs["num_steps"] == STEPS and metadata.run.inputs["noise_seed"] == SEED


def test_adarms_rows_are_the_conditioning_of_each_step(inputs, reference, tmp_path):
    _, record = reference
    capture(inputs[2], REPO_ID, tmp_path / "run", action_settings(inputs, "adarms", layers=(1,)))
    stored = load_layer(tmp_path / "run", 1, "adarms")
    expected = torch.stack([record["adarms", s] for s in range(STEPS)]).repeat(FRAMES, 1)
    torch.testing.assert_close(stored["residuals"].double(), expected, rtol=1e-5, atol=1e-5)
    assert stored["step"].tolist() == list(range(STEPS)) * FRAMES
    assert set(stored["token_position"].tolist()) == {-1}


def test_recapture_and_resume_are_byte_identical(inputs, decision_run, tmp_path):
    run_dir = tmp_path / "run"
    capture(inputs[2], REPO_ID, run_dir, action_settings(inputs, episodes_per_shard=1, num_workers=1))
    files = sorted(p.relative_to(decision_run) for p in decision_run.glob("decision/*/*.safetensors"))
    assert len(files) == 4 * len(LAYERS)
    assert all(sha256_file(run_dir / f) == sha256_file(decision_run / f) for f in files)
    (run_dir / files[1]).unlink()  # one shard lost: only its group is recomputed, with the same bytes
    result = capture(inputs[2], REPO_ID, run_dir, action_settings(inputs))
    assert result.written == (files[1].stem.removeprefix("shard-"),) and len(result.skipped) == 3
    assert sha256_file(run_dir / files[1]) == sha256_file(decision_run / files[1])
    with pytest.raises(ValueError, match="differs in inputs"):  # another seed is another run
        capture(inputs[2], REPO_ID, run_dir, action_settings(inputs, noise_seed=SEED + 1))


def test_slicing_decision_rows_per_concept(inputs, decision_run, tmp_path):
    dataset = inputs[2]
    first = [sum(frames for frames, _ in EPISODES[:e]) for e in range(len(EPISODES))]

    def segment(episode, start, end):
        return dict(segment_id=episode, episode_index=episode, frame_start=start, frame_end=end,
                    observed_frame_start=start, observed_frame_end=end, start_index=first[episode] + start,
                    end_index=first[episode] + end, length=end - start + 1)

    concepts = {"open": [segment(0, 0, 2), segment(2, 1, 3)], "bowl": [segment(3, 0, 1)]}
    concept_map = tmp_path / "map.json"
    concept_map.write_text(json.dumps({
        "manifest": "manifests/test.json", "lerobot_root": str(dataset), "repo_id": REPO_ID,
        "concept_count": {name: len(s) for name, s in concepts.items()}, "sample_count": FRAMES,
        "concepts": concepts,
    }))
    slice_concepts(decision_run, concept_map, tmp_path / "tokens", SliceSettings(layers=(0,), token_type="decision"))
    slice_concepts(decision_run, concept_map, tmp_path / "frames",
                   SliceSettings(layers=(0,), token_type="decision", reduce="frame"))
    stored = load_layer(decision_run, 0, "decision")
    for name, segments in concepts.items():
        frames = [s["start_index"] + k for s in segments for k in range(s["length"])]
        rows = [r for r, index in enumerate(stored["index"].tolist()) if index in frames]
        sliced = torch.load(tmp_path / "tokens" / "layer00" / f"{name}.pt", weights_only=True)
        assert torch.equal(sliced, stored["residuals"][rows])
        means = torch.load(tmp_path / "frames" / "layer00" / f"{name}.pt", weights_only=True)
        expected = stored["residuals"][rows].double().view(len(frames), STEPS, -1).mean(dim=1)
        torch.testing.assert_close(means.double(), expected, rtol=1e-6, atol=1e-6)
    with pytest.raises(ValueError, match="captured `decision` tokens, not `instructions`"):
        slice_concepts(decision_run, concept_map, tmp_path / "wrong", SliceSettings(layers=(0,)))


def test_bad_action_settings(inputs, tmp_path):
    run_dir = tmp_path / "run"
    beyond = rf"layers \[{EXPERT_DEPTH}\] out of range: the action expert \(decision token type\) has " \
             rf"{EXPERT_DEPTH} decoder layers \(0..{EXPERT_DEPTH - 1}\)"
    with pytest.raises(ValueError, match=beyond):
        capture(inputs[2], REPO_ID, run_dir, action_settings(inputs, layers=(0, EXPERT_DEPTH)))
    with pytest.raises(ValueError, match="num_steps"):
        action_settings(inputs, num_steps=0)
    assert not run_dir.exists()


def test_decision_shard_without_its_step_column_is_refused(decision_run, tmp_path):
    from safetensors.torch import load_file, save_file

    path = next(decision_run.glob("decision/layer00/*.safetensors"))
    tensors = load_file(path)
    del tensors["step"]
    header = json.dumps({"format_version": shards.FORMAT_VERSION, "layer": 0, "key": "00000",
                         "token_type": "decision"})
    save_file(tensors, str(tmp_path / "bad.safetensors"), metadata={shards.HEADER_KEY: header})
    with pytest.raises(ValueError, match=r"tensors missing \['step'\]"):
        with shards.open_shard(tmp_path / "bad.safetensors"):
            pass


def test_capture_command_decision(inputs, tmp_path):
    from typer.testing import CliRunner

    from latent_steering_cli.capture import app

    checkpoint, tokenizer, dataset = inputs
    arch_file = tmp_path / "arch.json"
    arch_file.write_text(ARCH.model_dump_json())
    args = ["capture", "--checkpoint-path", str(checkpoint), "--output-dir", str(tmp_path / "run"),
            "--lerobot-root", str(dataset), "--repo-id", REPO_ID, "--tokenizer-path", str(tokenizer),
            "--token-type", "decision", "--layers", "1", "--num-steps", "2", "--noise-seed", "3",
            "--device", "cpu", "--num-workers", "0", "--arch-file", str(arch_file)]
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 0, result.output
    stored = load_layer(tmp_path / "run", 1, "decision")
    assert stored["residuals"].shape == (FRAMES * 2, EXPERT.width)
    assert shards.read_run_metadata(tmp_path / "run").run.inputs["noise_seed"] == 3
