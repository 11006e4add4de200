"""lerobot's pi0.5 folder through the pipeline's entry points: capture, the server (against the same weights in
openpi's layout) and a closed-loop rollout in the LIBERO simulator, on the tiny model of tests/fixtures/lerobot_golden."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
import torch
from helpers_capture import make_lerobot_dataset
from helpers_serve import fixed_threads, libero_observations, running, write_vectors
from safetensors.numpy import load_file as load_numpy
from safetensors.torch import load_file, save_file
from test_lerobot_golden import ARCH, MODEL, SENTENCEPIECE, TOKENIZER_JSON
from websockets.sync.client import connect

from steering_core.capture import CaptureSettings, capture
from steering_core.capture.shards import read_run_metadata
from steering_core.pi05.layouts import LEROBOT
from steering_core.pi05.policy import Pi05Policy
from steering_core.pi05.spec import ModelSpec
from steering_core.serve import PolicyServer, SteeredPi05Policy, VectorCatalog
from steering_core.serve.codec import pack, unpack

REPO_ID = "local/dataset"
SEED = 7
EMBED_TOKENS = "paligemma_with_expert.paligemma.model.language_model.embed_tokens.weight"
LM_HEAD = "paligemma_with_expert.paligemma.lm_head.weight"


def openpi_copy(folder):
    """Write lerobot's weights in openpi's layout: bare keys, the embedding table (lerobot's embed_tokens) stored as
    openpi's lm_head, openpi's config.json and a norm_stats.json of the same quantiles."""
    tensors = {key.removeprefix("model."): value for key, value in load_file(str(MODEL / "model.safetensors")).items()}
    tensors[LM_HEAD] = tensors.pop(EMBED_TOKENS)
    folder.mkdir()
    save_file(tensors, str(folder / "model.safetensors"))
    (folder / "config.json").write_text(json.dumps({"action_dim": 32, "action_horizon": 10, "paligemma_variant": "dummy",
                                                     "action_expert_variant": "dummy", "precision": "float32"}))
    stats = load_numpy(str(MODEL / "policy_postprocessor_step_0_unnormalizer_processor.safetensors"))
    entries = {name: {stat: stats[f"{key}.{stat}"].astype(float).tolist() for stat in ("mean", "std", "q01", "q99")}
               for name, key in (("state", "observation.state"), ("actions", "action"))}
    assets = folder / "assets" / "physical-intelligence" / "libero"
    assets.mkdir(parents=True)
    (assets / "norm_stats.json").write_text(json.dumps({"norm_stats": entries}))
    return folder


@pytest.fixture(autouse=True)
def one_thread():
    with fixed_threads():
        yield


def test_capture_reads_a_lerobot_folder_and_records_its_layout(tmp_path):
    dataset = make_lerobot_dataset(tmp_path / "dataset", [(3, "open the top drawer"), (2, "close the top drawer")])
    settings = CaptureSettings(model=ModelSpec(checkpoint=MODEL, tokenizer=TOKENIZER_JSON, arch=ARCH), layers=(1,),
                               batch_size=4, device="cpu", num_workers=0)
    capture(dataset, REPO_ID, tmp_path / "run", settings)
    run = read_run_metadata(tmp_path / "run").run
    assert run.inputs["layout"] == "lerobot" and run.inputs["prompt_format"] == "discrete_state"
    assert run.inputs["max_token_len"] == 96 and run.inputs["norm_stats_sha256"] is not None

    # the rows are the prefix residuals of lerobot's own prompt (task and state) at the instruction tokens
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    items = [LeRobotDataset(REPO_ID, root=dataset)[i] for i in range(5)]
    policy = Pi05Policy.from_checkpoint(MODEL, ARCH, device="cpu", tokenizer_path=TOKENIZER_JSON)
    images, masks = policy.cameras.from_float(torch.stack([item["image"] for item in items]),
                                              torch.stack([item["wrist_image"] for item in items]), ARCH.image_size)
    tokens, token_mask = policy.tokenize([item["task"] for item in items],
                                         torch.stack([item["state"] for item in items]).numpy())
    direct = policy.prefix.residuals(images, masks, tokens, token_mask, [1])[1]
    shard = [load_file(str(path)) for path in sorted((tmp_path / "run" / "instructions" / "layer01").glob("*.safetensors"))]
    rows = torch.cat([part["residuals"] for part in shard])
    frames, positions = (torch.cat([part[name] for part in shard]) for name in ("index", "token_position"))
    torch.testing.assert_close(rows, direct[frames, positions], rtol=1e-5, atol=1e-5)
    states = torch.stack([item["state"] for item in items]).numpy()
    assert len({tuple(row) for row in states}) == 5  # every frame's own state reaches its prompt


def test_the_server_gives_lerobots_folder_and_openpis_copy_the_same_actions(tmp_path):
    """The same weights in both layouts (lerobot's embed_tokens as openpi's table), the same observations, plain and
    steered: the same actions within float32 rounding (openpi's quantiles add 1e-6, lerobot's do not)."""
    lerobot = Pi05Policy.from_checkpoint(MODEL, ARCH, device="cpu", tokenizer_path=TOKENIZER_JSON)
    openpi = Pi05Policy.from_checkpoint(openpi_copy(tmp_path / "openpi"), ARCH, device="cpu",
                                        tokenizer_path=SENTENCEPIECE, prompt_format="discrete_state", max_token_len=96)
    assert (lerobot.layout, openpi.layout) == ("lerobot", "openpi")
    observations = libero_observations(tmp_path / "demo", frames=2, image_size=ARCH.image_size)
    tokens = [policy.tokenize([obs["prompt"]], obs["observation/state"][None])[0] for obs in observations
              for policy in (lerobot, openpi)]
    assert all(torch.equal(a, b) for a, b in zip(tokens[::2], tokens[1::2]))  # the same prompt, state bins included
    catalog = VectorCatalog.scan(write_vectors(tmp_path / "vectors", ARCH.width))
    steer = {"pair": "open_vs_close", "layer": 1, "alpha": 4.0}
    replies = {}
    for name, policy in (("lerobot", lerobot), ("openpi", openpi)):
        served = SteeredPi05Policy(policy, noise_seed=SEED)
        with running(PolicyServer(served, catalog)) as server, \
                connect(f"ws://127.0.0.1:{server.port}", max_size=None) as ws:
            metadata = unpack(ws.recv())
            assert metadata["layout"] == name
            replies[name] = []
            for obs in observations:
                for request in (obs, obs | {"steering": steer}):
                    ws.send(pack(request))
                    replies[name].append(unpack(ws.recv(timeout=60))["actions"])
    for mine, theirs in zip(replies["lerobot"], replies["openpi"], strict=True):
        assert mine.shape == (10, 7)
        np.testing.assert_allclose(mine, theirs, rtol=0, atol=1e-4)
    assert np.abs(replies["lerobot"][1] - replies["lerobot"][0]).max() > 1e-3  # the steering moves the actions

    # reading lm_head as the table (openpi's convention) on lerobot's file is the trap: other actions, no error
    trap = shutil.copytree(tmp_path / "openpi", tmp_path / "trap")
    tensors = load_file(str(trap / "model.safetensors"))
    tensors[LM_HEAD] = load_file(str(MODEL / "model.safetensors"))["model." + LM_HEAD]
    save_file(tensors, str(trap / "model.safetensors"))
    wrong = Pi05Policy.from_checkpoint(trap, ARCH, device="cpu", tokenizer_path=SENTENCEPIECE,
                                       prompt_format="discrete_state", max_token_len=96)
    noise = torch.randn(10, 32, generator=torch.Generator().manual_seed(SEED))
    plain = lerobot.infer(observations[0], noise=noise)["actions"]
    assert np.abs(wrong.infer(observations[0], noise=noise)["actions"] - plain).max() > 1e-2
    assert LEROBOT.embedding_keys[0] == EMBED_TOKENS


@pytest.mark.slow
def test_a_libero_episode_of_the_lerobot_policy_runs_through_rollout(tmp_path):
    from steering_core.config import RolloutSection, load_run_config, write_run_config
    from steering_core.config.run import RunConfig
    from steering_core.config.sections import DatasetSection, ModelSection, PairSection, SourcesSection
    from steering_core.rollout.local_run import rollout_config
    from steering_core.rollout.records import read_cell
    from steering_core.rollout.settings import LiberoTask, RolloutPair

    pair = "open_vs_close"
    write_vectors(tmp_path / "data" / "latent_steering", ARCH.width)
    tasks = RolloutPair(positive=LiberoTask(suite="libero_goal", task="open the middle drawer of the cabinet"),
                        negative=LiberoTask(suite="libero_goal", task=7))
    config = RunConfig(
        output_root=tmp_path / "data", sources=SourcesSection(folders=(tmp_path / "demos",)),
        dataset=DatasetSection(repo_id="unused"),
        pairs=(PairSection(name=pair, positive="open the top drawer of the cabinet",
                           negative="close the top drawer of the cabinet"),),
        layers=(1,), model=ModelSection(checkpoint=MODEL, tokenizer=TOKENIZER_JSON, arch=ARCH), evaluate=None,
        rollout=RolloutSection(pairs={pair: tasks}, alphas=(0, 2), episodes=1, chunk_episodes=1, max_steps=12,
                               sides=("negative",), random_directions=0, wrong_concept=False, instruction_swap=False,
                               device="cpu", note="tiny random lerobot-layout policy"),
    )
    path = write_run_config(config, tmp_path / "run.yaml")
    summaries = rollout_config(load_run_config(path))
    assert list(summaries) == [1]
    for cell in ("negative_unsteered_a+0", "negative_sae_a+2"):
        record, arrays = read_cell(config.rollout_layer_path(1) / pair / cell)
        [episode] = record["episodes"]
        assert episode["init_index"] == 0 and arrays["lengths"][0] > 0
        assert np.isfinite(arrays["actions"][0, : arrays["lengths"][0]]).all()


def test_the_evaluation_prompts_each_frame_with_its_own_state(tmp_path):
    """lerobot's prompt carries the state: the sweep's unsteered and swapped actions of each frame are the policy's
    own on that frame's prompt (its task and state), and two frames of one task get different tokens."""
    from steering_core.evaluate.frames import EvalFrame
    from steering_core.evaluate.run import PolicyPrompts
    from steering_core.evaluate.sweep import frame_noise, run_sweep
    from steering_core.pi05.steering import Steering

    policy = Pi05Policy.from_checkpoint(MODEL, ARCH, device="cpu", tokenizer_path=TOKENIZER_JSON)
    tasks = {"positive": "open the top drawer", "negative": "close the top drawer"}
    frames = [EvalFrame("negative", 0, t, t) for t in range(2)] + [EvalFrame("positive", 1, 0, 2)]
    generator = torch.Generator().manual_seed(0)
    images = [torch.rand(3, 3, 28, 28, generator=generator) * 2 - 1 for _ in range(2)] + [torch.full((3, 3, 28, 28), -1.0)]
    masks = [torch.ones(3, dtype=torch.bool)] * 2 + [torch.zeros(3, dtype=torch.bool)]
    states = np.random.default_rng(0).uniform(-1, 1, (3, 8))
    prompts = PolicyPrompts(policy, tasks)
    negative = prompts.of("negative", states[:2], 2)
    assert not torch.equal(negative.tokens[0], negative.tokens[1])  # each frame's state bins
    assert torch.equal(negative.instruction_mask[0], negative.instruction_mask[1])
    actions = run_sweep(policy, Steering, frames, lambda _: {"images": images, "image_masks": masks, "states": states},
                        prompts, {"d": torch.randn(ARCH.width, generator=generator)}, layer=1, alphas=(0.0, 2.0),
                        mean_residual_norm=1.0, noise_seeds=1, seed=0, num_steps=2, batch_size=2, entries_per_call=4)
    for i, frame in enumerate(frames):
        noise = frame_noise(frame, 0, 0, policy.action_horizon, policy.action_dim)[None]
        for side, expected in ((frame.side, actions.own[i, 0]),
                               ("positive" if frame.side == "negative" else "negative",
                                actions.own[i, 0] + actions.swap[i, 0])):
            tokens, token_mask = policy.tokenize([tasks[side]], states[i : i + 1])
            alone = policy.sample_actions([t[i : i + 1] for t in images], [m[i : i + 1] for m in masks], tokens,
                                          token_mask, noise=noise, num_steps=2)
            np.testing.assert_allclose(policy.robot_actions(alone)[0], expected.numpy(), rtol=0, atol=1e-4)
    assert (actions.steered[0, 1] - actions.own).abs().max() > 1e-3  # the steering moves them
