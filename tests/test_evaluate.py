"""Steering evaluation: planted answer on a fake policy, held-out split, frames, grid, metrics, outputs, errors."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch
from helpers_evaluate import INSTRUCTION, NEGATIVE_IDS, POSITIVE_IDS, FakePolicy, FakeSteering, load, prompts
from safetensors.torch import load_file, save_file

from steering_core.data.concept_map import ConceptMap, ConceptRow
from steering_core.data.contrast import AxisSummary, ContrastManifest, Segment
from steering_core.data.split import read_split, split_episodes, write_split
from steering_core.evaluate import EvaluateSettings
from steering_core.evaluate.directions import decision_directions
from steering_core.evaluate.frames import evenly_spaced, select_frames
from steering_core.evaluate.metrics import dose_response_metrics, episode_weights, state_axis_weights
from steering_core.evaluate.pair import PairInputs, evaluate_pair
from steering_core.evaluate.report import write_layer_summary, write_pathways

POS, NEG = "open the drawer", "close the drawer"
EPISODE_FRAMES, WINDOW = 12, (2, 9)
WIDTH, LAYER, NORM = 256, 2, 5.0
GAP = 2 * NORM  # the instruction swap moves the residual by 2 R along the planted direction: α* = 2


def manifest(episodes: dict[str, list[int]]) -> ContrastManifest:
    segments = [Segment(task=task, file="data.parquet", demo=f"episode_{e:06d}", start_step=WINDOW[0],
                        end_step=WINDOW[1], axis_delta=0.1, axis_values=(0.0,) * (WINDOW[1] - WINDOW[0] + 1),
                        episode_index=e)
                for task, members in episodes.items() for e in members]
    axis = AxisSummary(index=2, effect_size=3.0, mean_delta_per_task={POS: -0.2, NEG: 0.2})
    return ContrastManifest(axis=axis, segments=tuple(segments))


def concept_map(m: ContrastManifest) -> ConceptMap:
    concepts: dict[str, list[ConceptRow]] = {}
    for i, seg in enumerate(m.segments):
        start = seg.episode_index * EPISODE_FRAMES + seg.start_step
        concepts.setdefault(seg.task, []).append(ConceptRow(
            segment_id=i, episode_index=seg.episode_index, frame_start=seg.start_step, frame_end=seg.end_step,
            observed_frame_start=seg.start_step, observed_frame_end=seg.end_step, start_index=start,
            end_index=start + seg.end_step - seg.start_step, length=seg.end_step - seg.start_step + 1))
    return ConceptMap(manifest="m.json", lerobot_root="root", repo_id="r",
                      concept_count={c: len(r) for c, r in concepts.items()}, sample_count=10 * EPISODE_FRAMES,
                      concepts={c: tuple(r) for c, r in concepts.items()})


EPISODES = {POS: [0, 1, 2, 3, 4], NEG: [5, 6, 7, 8, 9]}


def slices(folder: Path) -> tuple[Path, Path]:
    """Two concept slices whose rows all have norm NORM (the α unit)."""
    rows = [torch.randn(20, WIDTH, generator=torch.Generator().manual_seed(i)) for i in range(2)]
    return write_slices(folder, *(r / r.norm(dim=-1, keepdim=True) * NORM for r in rows))


def write_slices(folder: Path, positive: torch.Tensor, negative: torch.Tensor) -> tuple[Path, Path]:
    """Write two concept slices as slicing does (.pt + .safetensors `residuals` and `episode_index`, rows
    spread over three training episodes of each task); return their .pt paths."""
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for name, rows, episodes in (("pos", positive, EPISODES[POS]), ("neg", negative, EPISODES[NEG])):
        path = folder / f"{name}.pt"
        torch.save(rows, path)
        episode_index = torch.tensor(episodes[:3] * len(rows))[: len(rows)].sort().values
        save_file({"residuals": rows, "episode_index": episode_index}, str(path.with_suffix(".safetensors")))
        paths.append(path)
    return paths[0], paths[1]


def planted() -> torch.Tensor:
    return torch.randn(WIDTH, generator=torch.Generator().manual_seed(7))


def run(tmp_path: Path, out: Path, *, fraction: float = 0.4, saturate: bool = False, sign: float = 1.0,
        include_decoder_bias: bool = False, **overrides) -> tuple[Path, FakePolicy]:
    m = manifest(EPISODES)
    pair = PairInputs(name="open_vs_close", tasks=(POS, NEG), manifest=m, concept_map=concept_map(m),
                      split=split_episodes(m, fraction), slices=slices(tmp_path / "slices"))
    u = planted()
    directions = {"sae": sign * u * 3.0, "mean_difference": sign * u + 0.01 * torch.ones(WIDTH)}
    policy = FakePolicy(WIDTH, u, GAP, saturate=saturate)
    settings = EvaluateSettings(**{"max_frames": 8, "noise_seeds": 2, "bootstrap": 200, "batch_size": 3,
                                   "device": "cpu", "random_directions": 8, "permutations": 4, "modes": ("add",)} | overrides)
    evaluate_pair(pair, directions, policy, FakeSteering, load, prompts(), layer=LAYER, width=WIDTH,
                  settings=settings, output_dir=out, metadata={"policy": "fake"},
                  include_decoder_bias=include_decoder_bias)
    return out, policy


def test_planted_direction_reproduces_the_swap_and_random_ones_do_not(tmp_path):
    out, policy = run(tmp_path, tmp_path / "eval" / "open_vs_close")
    record = json.loads((out / "dose_response.json").read_text())
    alphas = record["alphas"]
    at = alphas.index(2.0)
    planted_entry = record["directions"]["sae"]
    for side in ("", "_positive", "_negative"):
        assert planted_entry[f"efficacy{side}"][at] == pytest.approx(1.0, abs=0.05)
        low, high = planted_entry[f"efficacy{side}_ci"][at]
        assert low - 1e-6 <= 1.0 <= high + 1e-6 and high - low < 0.2
    best = planted_entry["best"]
    assert best["alpha"] == 2.0 and best["reversed"] is False and best["selected_alphas"] == [2.0, 2.0]
    assert best["efficacy"] == pytest.approx(1.0, abs=0.05)
    assert planted_entry["cosine"][at] > 0.95
    # linear in α: half the dose, half the effect; the opposite sign moves the other way
    assert planted_entry["efficacy"][alphas.index(1.0)] == pytest.approx(0.5, abs=0.05)
    assert planted_entry["efficacy"][alphas.index(-2.0)] == pytest.approx(-1.0, abs=0.05)
    # α in vector units: α R / ||d|| with ||d|| = 3 ||u||
    norm = 3.0 * float(planted().norm())
    assert planted_entry["alphas_vector_units"][at] == pytest.approx(2.0 * NORM / norm, rel=1e-5)
    assert best["alpha_vector"] == pytest.approx(2.0 * NORM / norm, rel=1e-5)
    assert best["request"] == {"pair": "open_vs_close", "layer": LAYER, "direction": "sae",
                               "alpha": best["alpha_vector"], "alpha_units": "vector"}
    assert record["mean_residual_norm"] == pytest.approx(NORM, rel=1e-6)
    assert len(record["random"]["names"]) == 8 and len(record["random"]["permuted"]) == 4
    for name in record["random"]["names"] + record["random"]["permuted"]:
        assert abs(record["directions"][name]["efficacy"][at]) < 0.25
    assert planted_entry["z"][at] > 5
    # the planted direction beats every null: the smallest p a null of N can give, 1 / (1 + N)
    assert planted_entry["p_random"][at] == pytest.approx(1 / 9) and best["p_random"] == pytest.approx(1 / 9)
    assert best["p_permuted"] == pytest.approx(1 / 5)
    assert planted_entry["efficacy"][alphas.index(0.0)] == 0.0
    # the contrast axis (state z -> action z), toward the other task, integrated over the horizon
    assert planted_entry["contrast_shift"][at] == pytest.approx(record["swap"]["contrast_shift"], rel=0.1)
    # one sweep per (batch, seed) with the α = 0 entry shared: 1 + directions x nonzero alphas entries
    frames = len(record["frames"])
    batches = sum(-(-sum(f["side"] == s for f in record["frames"]) // 3) for s in ("positive", "negative"))
    directions = 2 + 8 + 4
    assert policy.calls == {"sweep_calls": batches * 2 * -(-directions * 8 // 40),
                            "sweep_entries": batches * 2 * (1 + directions * 8),
                            "sample_actions": batches * 2}
    assert frames == 8
    tensors = load_file(out / "dose_response.safetensors")
    assert tensors["actions"].shape == (directions, 9, 8, 2, 4, 7)
    assert torch.allclose(tensors["efficacy"][0], torch.tensor(planted_entry["efficacy"], dtype=torch.float32))
    for png in ("efficacy_vs_alpha.png", "shift_vs_alpha.png", "trajectory.png"):
        assert (out / png).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_saturating_policy_scores_one_on_both_sides(tmp_path):
    """Each instruction sits on a plateau of tanh: steering each frame toward the other task reproduces its swap,
    while pushing a frame past its own instruction (+α on positive-task frames) would change nothing (≈ 0.5)."""
    out, _ = run(tmp_path, tmp_path / "eval" / "p", saturate=True)
    record = json.loads((out / "dose_response.json").read_text())
    entry, at = record["directions"]["sae"], record["alphas"].index(2.0)
    assert entry["efficacy_negative"][at] == pytest.approx(1.0, abs=0.02)
    assert entry["efficacy_positive"][at] == pytest.approx(1.0, abs=0.02)
    assert entry["efficacy"][at] == pytest.approx(1.0, abs=0.02)
    assert entry["efficacy"][record["alphas"].index(4.0)] == pytest.approx(1.0, abs=0.02)  # past it: the plateau


def test_frames_come_from_held_out_episodes_inside_the_windows(tmp_path):
    out, _ = run(tmp_path, tmp_path / "eval" / "p")
    record = json.loads((out / "dose_response.json").read_text())
    split = record["split"]["tasks"]
    held = {side: set(split[task]["holdout"]) for side, task in (("positive", POS), ("negative", NEG))}
    assert record["in_sample"] is False and record["split"]["holdout_fraction"] == 0.4
    for frame in record["frames"]:
        assert frame["episode_index"] in held[frame["side"]]
        assert WINDOW[0] <= frame["frame_index"] <= WINDOW[1]
        assert frame["index"] == frame["episode_index"] * EPISODE_FRAMES + frame["frame_index"]
    assert [f["side"] for f in record["frames"]] == ["positive"] * 4 + ["negative"] * 4


def test_same_inputs_give_byte_identical_outputs(tmp_path):
    first, _ = run(tmp_path, tmp_path / "a" / "p")
    second, _ = run(tmp_path, tmp_path / "b" / "p")
    names = sorted(p.name for p in first.iterdir())
    assert names == sorted(p.name for p in second.iterdir())
    for name in names:
        assert (first / name).read_bytes() == (second / name).read_bytes(), name


def test_in_sample_evaluation_says_so(tmp_path):
    out, _ = run(tmp_path, tmp_path / "eval" / "p", fraction=0.0, note="tiny model: numbers mean nothing")
    record = json.loads((out / "dose_response.json").read_text())
    assert record["in_sample"] is True
    assert {f["episode_index"] for f in record["frames"]} <= set(EPISODES[POS] + EPISODES[NEG])
    md = write_layer_summary(out.parent, ["p"]).read_text()
    assert "in-sample" in md and "tiny model: numbers mean nothing" in md
    assert "| p | sae | add | 2 / " in md


def test_efficacy_plot_takes_an_interval_that_misses_its_estimate_by_rounding(tmp_path):
    from steering_core.evaluate.plots import plot_efficacy

    out, _ = run(tmp_path, tmp_path / "eval" / "p")
    record = json.loads((out / "dose_response.json").read_text())
    entry = record["directions"]["sae"]
    entry["efficacy_ci"] = [[v + 1e-12, v + 1e-12] for v in entry["efficacy"]]  # one episode per side, rounded
    plot_efficacy(tmp_path / "efficacy.png", record)
    assert (tmp_path / "efficacy.png").read_bytes()[:4] == b"\x89PNG"


def test_decoder_bias_vectors_are_marked(tmp_path):
    plain, _ = run(tmp_path, tmp_path / "plain" / "p")
    assert json.loads((plain / "dose_response.json").read_text())["include_decoder_bias"] is False
    assert "include-decoder-bias" not in write_layer_summary(plain.parent, ["p"]).read_text()
    biased, _ = run(tmp_path, tmp_path / "biased" / "p", include_decoder_bias=True)
    assert json.loads((biased / "dose_response.json").read_text())["include_decoder_bias"] is True
    assert "written with --include-decoder-bias" in write_layer_summary(biased.parent, ["p"]).read_text()


def test_split_is_deterministic_per_task_and_keeps_one_on_each_side(tmp_path):
    m = manifest(EPISODES)
    split = split_episodes(m, 0.2)
    assert split == split_episodes(m, 0.2)
    for task, members in EPISODES.items():
        side = split.tasks[task]
        assert len(side.holdout) == 1 and sorted(side.train + side.holdout) == members
    # an episode's side depends on the episode alone: adding demos of the other task changes nothing here
    grown = split_episodes(manifest({POS: EPISODES[POS], NEG: EPISODES[NEG] + [10, 11, 12]}), 0.2)
    assert grown.tasks[POS] == split.tasks[POS]
    assert split_episodes(m, 0.0).holdout_episodes == ()
    write_split(split, tmp_path / "split.json")
    assert read_split(tmp_path / "split.json") == split
    with pytest.raises(ValueError, match=r"task 'close the drawer' has 1 episode\(s\) \[5\].*holdout_fraction: 0"):
        split_episodes(manifest({POS: [0, 1], NEG: [5]}), 0.2)


def test_evenly_spaced_and_frame_budget():
    assert evenly_spaced(10, 4) == [0, 2, 5, 7]
    assert evenly_spaced(3, 4) == [0, 1, 2]
    m = manifest(EPISODES)
    frames = select_frames(m, concept_map(m), split_episodes(m, 0.2), (POS, NEG), 5)
    assert [f.side for f in frames] == ["positive"] * 3 + ["negative"] * 2


def metrics_of(steered, swap, toward, episodes, halves, scale=None, axis=0, samples=50):
    return dose_response_metrics(
        steered, swap, scale=torch.ones(7, dtype=torch.float64) if scale is None else scale,
        contrast=state_axis_weights(axis), toward=torch.tensor(toward, dtype=torch.float64),
        halves=torch.tensor(halves), episodes=episodes, zero_index=0, samples=samples, seed=0)


def test_metrics_against_a_hand_computed_case():
    """Two frames (a negative-task one, a positive-task one), one seed, horizon 1; action std 4 on the gripper."""
    steered = torch.zeros(1, 2, 2, 1, 1, 7, dtype=torch.float64)
    steered[0, 1, 0, 0, 0, 0] = 1.0   # frame 0 moves x by 1
    steered[0, 1, 1, 0, 0, 6] = 3.0   # frame 1 moves the gripper by 3
    swap = torch.zeros(2, 1, 1, 7, dtype=torch.float64)
    swap[0, 0, 0, 0] = 2.0            # frame 0: swap moves x by 2
    swap[1, 0, 0, 6] = 1.0            # frame 1: swap moves the gripper by 1
    scale = torch.tensor([1.0, 1, 1, 1, 1, 1, 4.0], dtype=torch.float64)
    out = metrics_of(steered, swap, [1.0, -1.0], [0, 1], [0, 1], scale)
    # in std units: frame 0 <Δa, swap> = 2, ||swap||² = 4; frame 1: (3/4)(1/4) = 3/16, 1/16
    assert out["efficacy"][0, 1] == pytest.approx((2 + 3 / 16) / (4 + 1 / 16))
    assert out["efficacy_raw"][0, 1] == pytest.approx((2 + 3) / (4 + 1))
    assert out["efficacy_negative"][0, 1] == pytest.approx(0.5)
    assert out["efficacy_positive"][0, 1] == pytest.approx(3.0)
    # one episode per side: every episode resample is the data itself
    assert out["efficacy_ci"][0, 1].tolist() == pytest.approx([float(out["efficacy"][0, 1])] * 2)
    assert out["cosine"][0, 1] == pytest.approx(1.0)
    assert out["shift"][0, 1].tolist() == pytest.approx([0.5, 0, 0, 0, 0.375])
    assert out["shift_raw"][0, 1].tolist() == pytest.approx([0.5, 0, 0, 0, 1.5])
    # contrast on state x: frame 0 pushed toward the positive task (+1), frame 1 toward the negative (−1)
    assert out["contrast_shift"][0, 1] == pytest.approx(0.5)
    assert out["swap_contrast_shift"] == pytest.approx(1.0)
    assert out["efficacy"][0, 0] == 0.0
    # half 0 holds frame 0, half 1 frame 1: α = 1 is chosen on each, read on the other: (3 + 0.5) / 2
    assert out["efficacy_half"][:, 0, 1].tolist() == pytest.approx([0.5, 3.0])
    assert out["crossfit"][0] == pytest.approx(1.75)


def test_cross_fitting_chooses_alpha_on_one_half_and_reads_it_on_the_other():
    """Half 0 peaks at α index 1 (efficacy 1) while α index 2 gives 3; half 1 the other way round."""
    steered = torch.zeros(1, 3, 2, 1, 1, 7, dtype=torch.float64)
    swap = torch.zeros(2, 1, 1, 7, dtype=torch.float64)
    swap[:, 0, 0, 0] = 1.0
    steered[0, 1, :, 0, 0, 0] = torch.tensor([1.0, 3.0])  # frame 0 (half 0): 1; frame 1 (half 1): 3
    steered[0, 2, :, 0, 0, 0] = torch.tensor([3.0, 1.0])
    out = metrics_of(steered, swap, [1.0, 1.0], [0, 1], [0, 1])
    assert out["crossfit_alpha_index"][:, 0].tolist() == [1, 2]
    # chosen on half 0 (index 1) read on half 1: 3; chosen on half 1 (index 2) read on half 0: 3
    assert out["crossfit"][0] == pytest.approx(3.0) and out["crossfit_negative"][0] == pytest.approx(3.0)
    # choosing and scoring on all frames would have reported 2 for both α: no α is closest to 1 in truth
    assert out["efficacy"][0, 1:].tolist() == pytest.approx([2.0, 2.0])


def test_intervals_resample_episodes_not_frames():
    """Negative side: episode 0's three frames have efficacy 0, episode 1's three have 1. Resampling two episodes
    gives 0, 0.5 or 1 (1/4 each at the ends), so the 95% interval is [0, 1]; frames would give a narrower one."""
    steered = torch.zeros(1, 2, 6, 1, 1, 7, dtype=torch.float64)
    swap = torch.zeros(6, 1, 1, 7, dtype=torch.float64)
    swap[..., 0] = 1.0
    steered[0, 1, 3:, 0, 0, 0] = 1.0
    out = metrics_of(steered, swap, [1.0] * 6, [0, 0, 0, 1, 1, 1], [0, 0, 0, 1, 1, 1], samples=2000)
    assert out["efficacy_negative"][0, 1] == pytest.approx(0.5)
    assert out["efficacy_negative_ci"][0, 1].tolist() == pytest.approx([0.0, 1.0])
    weights = episode_weights([0, 0, 1, 2, 2, 3], ["negative"] * 3 + ["positive"] * 3, 100, 0)
    assert torch.equal(weights[:, 0], weights[:, 1]) and torch.equal(weights[:, 3], weights[:, 4])
    # each frame weighs its episode's draws; per side as many draws as episodes
    assert (weights[:, 0] + weights[:, 2] == 2).all() and (weights[:, 3] + weights[:, 5] == 2).all()


def test_contrast_axis_maps_to_actions_at_libero_pose():
    """At LIBERO's rest orientation (π about x), hand-computed: J⁻¹ = x̂x̂ᵀ − (π/2)[x̂]×, so state axis 5 (r_z)
    moves by −π/2 per unit of action 4 (ω_y) and axis 4 (r_y) by +π/2 per unit of action 5 (ω_z)."""
    assert state_axis_weights(5).tolist() == pytest.approx([0, 0, 0, 0, -math.pi / 2, 0, 0], abs=1e-12)
    assert state_axis_weights(4).tolist() == pytest.approx([0, 0, 0, 0, 0, math.pi / 2, 0], abs=1e-12)
    assert state_axis_weights(3).tolist() == pytest.approx([0, 0, 0, 1, 0, 0, 0], abs=1e-12)
    assert state_axis_weights(1).tolist() == [0, 1, 0, 0, 0, 0, 0]
    assert state_axis_weights(6).tolist() == [0, 0, 0, 0, 0, 0, -1]  # closing (+1) shrinks the left finger
    assert state_axis_weights(7).tolist() == [0, 0, 0, 0, 0, 0, 1]   # the mirrored finger
    # against finite differences of the axis-angle of exp(εω) R0, through quaternions, near the pose
    r0 = np.array([math.pi - 0.05, 0.02, -0.01])
    for action in range(3):
        omega = np.zeros(3)
        omega[action] = 1e-6
        numeric = (axis_angle(rotation(omega) @ rotation(r0)) - axis_angle(rotation(r0))) / 1e-6
        expected = [float(state_axis_weights(3 + k, tuple(r0))[3 + action]) for k in range(3)]
        assert numeric.tolist() == pytest.approx(expected, abs=1e-4)


def rotation(r: np.ndarray) -> np.ndarray:
    """Rodrigues: the rotation matrix of an axis-angle."""
    theta = np.linalg.norm(r)
    k = np.array([[0, -r[2], r[1]], [r[2], 0, -r[0]], [-r[1], r[0], 0]]) / theta
    return np.eye(3) + math.sin(theta) * k + (1 - math.cos(theta)) * k @ k


def axis_angle(m: np.ndarray) -> np.ndarray:
    """The axis-angle of a rotation matrix through its unit quaternion (w ≥ 0)."""
    w = math.sqrt(max(0.0, 1 + np.trace(m))) / 2
    xyz = np.sqrt(np.maximum(0.0, 1 + 2 * np.diag(m) - np.trace(m))) / 2
    signs = np.sign([m[2, 1] - m[1, 2], m[0, 2] - m[2, 0], m[1, 0] - m[0, 1]])
    largest = int(np.argmax(xyz))  # fix the signs against the largest component (w is near 0 here)
    off = {(0, 1): m[0, 1] + m[1, 0], (0, 2): m[0, 2] + m[2, 0], (1, 2): m[1, 2] + m[2, 1]}
    for k in range(3):
        if k != largest:
            xyz[k] = math.copysign(xyz[k], off[tuple(sorted((k, largest)))])
    xyz *= signs[largest] if signs[largest] != 0 else 1.0
    if w < 0:
        w, xyz = -w, -xyz
    angle = 2 * math.atan2(np.linalg.norm(xyz), w)
    return xyz / np.linalg.norm(xyz) * angle


def test_bad_input(tmp_path):
    with pytest.raises(ValueError, match="must include 0"):
        EvaluateSettings(alphas=(1.0, 2.0))
    with pytest.raises(ValueError, match="greater than or equal to 8"):
        EvaluateSettings(random_directions=4)
    m = manifest(EPISODES)
    pair = PairInputs(name="p", tasks=(POS, NEG), manifest=m, concept_map=concept_map(m),
                      split=split_episodes(m, 0.2), slices=slices(tmp_path / "s"))
    wrong = {"sae": torch.ones(WIDTH + 1), "random_00": torch.ones(WIDTH)}
    out = tmp_path / "eval" / "p"
    with pytest.raises(ValueError, match=r"sae.*\(257,\).*\(256,\)"):
        evaluate_pair(pair, wrong, FakePolicy(WIDTH, planted(), GAP), FakeSteering, load, prompts(), layer=LAYER,
                      width=WIDTH, settings=EvaluateSettings(), output_dir=out)
    assert not out.exists()


def test_model_checks_name_the_problem(tmp_path):
    from steering_core.capture import CaptureSettings
    from steering_core.evaluate.run import check_model
    from steering_core.pi05 import PromptFormat
    from steering_core.pi05.spec import ModelSpec
    from steering_core.synthetic.pi05 import tiny_arch, write_pi05_checkpoint

    arch = tiny_arch()
    spec = ModelSpec(checkpoint=tmp_path / "missing", tokenizer=tmp_path / "tok", arch=arch)
    model = CaptureSettings(model=spec, layers=(1,))
    with pytest.raises(FileNotFoundError, match="missing: policy checkpoint not found"):
        check_model(model, 1)
    write_pi05_checkpoint(tmp_path / "ckpt", arch)
    model = CaptureSettings(model=spec.model_copy(update={"checkpoint": tmp_path / "ckpt"}), layers=(1,))
    with pytest.raises(ValueError, match=rf"layer {arch.depth} is not a layer of the policy: it has {arch.depth}"):
        check_model(model, arch.depth)
    # a prompt carrying the state is evaluated frame by frame (tests/test_lerobot_layout.py): no refusal
    discrete = spec.model_copy(update={"checkpoint": tmp_path / "ckpt", "prompt_format": PromptFormat.DISCRETE_STATE})
    check_model(CaptureSettings(model=discrete, layers=(1,)), 1)
    # the last language-model layer only feeds the final norm: steering it cannot change the actions
    with pytest.raises(ValueError, match=rf"^layer {arch.depth - 1}: the last language-model layer's output only "
                                         rf"feeds the final norm.*; evaluate layers 0..{arch.depth - 2}$"):
        check_model(model, arch.depth - 1)
    check_model(model, arch.depth - 2)
    check_model(model, arch.depth - 1, "expert")  # the expert's last layer feeds the action projection


# ----------------------------------------------------------------------------- the action-expert pathway

EXPERT_WIDTH, EXPERT_LAYER, HALF_GAP = 128, 1, 3.0


def decision_slices(folder: Path, u: torch.Tensor) -> tuple[Path, Path]:
    """Decision slices of both tasks: rows ±HALF_GAP·û + w_i with the same w_i ⟂ û and every row of norm NORM,
    so the mean difference is exactly 2·HALF_GAP·û and the α unit is NORM."""
    unit = u.double() / u.double().norm()
    w = torch.randn(30, EXPERT_WIDTH, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    w = w - (w @ unit)[:, None] * unit
    w = w / w.norm(dim=-1, keepdim=True) * (NORM**2 - HALF_GAP**2) ** 0.5
    return write_slices(folder, (HALF_GAP * unit + w).float(), (-HALF_GAP * unit + w).float())


def expert_planted() -> torch.Tensor:
    return torch.randn(EXPERT_WIDTH, generator=torch.Generator().manual_seed(11))


def run_expert(tmp_path: Path, out: Path, *, width: int = EXPERT_WIDTH) -> tuple[Path, FakePolicy]:
    """The expert pathway on a fake policy whose actions read the expert residual along the planted direction."""
    m = manifest(EPISODES)
    u = expert_planted()
    pair = PairInputs(name="open_vs_close", tasks=(POS, NEG), manifest=m, concept_map=concept_map(m),
                      split=split_episodes(m, 0.4), slices=decision_slices(tmp_path / "decision", u))
    directions = {name: d.direction for name, d in decision_directions(pair.slices, "open_vs_close", EXPERT_LAYER).items()}
    policy = FakePolicy(EXPERT_WIDTH, u, GAP, stream="expert")
    settings = EvaluateSettings(max_frames=8, noise_seeds=2, bootstrap=200, batch_size=3, device="cpu",
                                random_directions=8, permutations=4, modes=("add",))
    evaluate_pair(pair, directions, policy, FakeSteering, load, prompts(), layer=EXPERT_LAYER, width=width,
                  settings=settings, output_dir=out, metadata={"policy": "fake"}, stream="expert")
    return out, policy


def test_planted_expert_direction_reproduces_the_swap_and_random_ones_do_not(tmp_path):
    out, policy = run_expert(tmp_path, tmp_path / "eval" / "expert_layer01" / "open_vs_close")
    record = json.loads((out / "dose_response.json").read_text())
    assert record["stream"] == "expert" and record["layer"] == EXPERT_LAYER
    assert record["alpha_units"]["alphas"].startswith("R, the mean residual norm of the training rows")
    assert list(record["directions"]) == (["mean_difference"] + [f"random_{i:02d}" for i in range(8)]
                                          + [f"permuted_{i:02d}" for i in range(4)])
    alphas = record["alphas"]
    at = alphas.index(2.0)  # the swap moves the expert residual by GAP = 2 R along the planted direction
    entry = record["directions"]["mean_difference"]
    assert entry["efficacy"][at] == pytest.approx(1.0, abs=0.05)
    low, high = entry["efficacy_ci"][at]
    assert low - 1e-6 <= 1.0 <= high + 1e-6 and high - low < 0.2
    assert entry["best"]["alpha"] == 2.0 and entry["z"][at] > 5 and entry["best"]["request"] is None
    assert entry["efficacy"][alphas.index(-2.0)] == pytest.approx(-1.0, abs=0.05)
    for name in record["random"]["names"]:
        assert abs(record["directions"][name]["efficacy"][at]) < 0.25
    # α unit: the decision rows' mean norm; the direction is the unit mean difference û, so vector units are α R
    assert record["mean_residual_norm"] == pytest.approx(NORM, rel=1e-5)
    assert record["direction_norms"]["mean_difference"] == pytest.approx(1.0, rel=1e-5)
    assert entry["alphas_vector_units"][at] == pytest.approx(2.0 * NORM, rel=1e-5)
    # random directions of equal norm, in expert width; the direction itself is kept with the outputs
    norms = record["direction_norms"]
    assert all(norms[n] == pytest.approx(1.0, rel=1e-5) for n in record["random"]["names"])
    tensors = load_file(out / "dose_response.safetensors")
    unit = expert_planted().double() / expert_planted().double().norm()
    assert tensors["directions"].shape == (13, EXPERT_WIDTH)
    torch.testing.assert_close(tensors["directions"][0].double(), unit, rtol=0, atol=1e-6)
    # one sweep per (batch, seed) and chunk of 40, α = 0 shared: 1 + 13 directions x 8 nonzero α entries
    batches = sum(-(-sum(f["side"] == s for f in record["frames"]) // 3) for s in ("positive", "negative"))
    assert policy.calls == {"sweep_calls": batches * 2 * 3, "sweep_entries": batches * 2 * (1 + 13 * 8),
                            "sample_actions": batches * 2}
    md = write_layer_summary(out.parent, ["open_vs_close"]).read_text()
    assert md.startswith("# Steering evaluation, expert_layer01") and "| open_vs_close | mean_difference | add | 2 / " in md


def test_expert_outputs_are_byte_identical_and_the_width_is_checked(tmp_path):
    first, _ = run_expert(tmp_path, tmp_path / "a" / "p")
    second, _ = run_expert(tmp_path, tmp_path / "b" / "p")
    names = sorted(p.name for p in first.iterdir())
    assert names == sorted(p.name for p in second.iterdir()) and "efficacy_vs_alpha.png" in names
    for name in names:
        assert (first / name).read_bytes() == (second / name).read_bytes(), name
    out = tmp_path / "c" / "p"
    with pytest.raises(ValueError, match=r"mean_difference.*\(128,\).*action expert.s residual width \(129,\)"):
        run_expert(tmp_path, out, width=EXPERT_WIDTH + 1)
    assert not out.exists()


def test_pathways_table_puts_the_best_lm_direction_beside_the_expert(tmp_path):
    root = tmp_path / "steering_eval"
    run(tmp_path, root / "layer02" / "open_vs_close")
    run_expert(tmp_path, root / "expert_layer01" / "open_vs_close")
    md = write_pathways(root, [(2, "lm"), (1, "expert")], ["open_vs_close"]).read_text()
    pathways = json.loads((root / "pathways.json").read_text())
    [row] = pathways["rows"]
    lm = json.loads((root / "layer02" / "open_vs_close" / "dose_response.json").read_text())
    # naive reference: every (direction, α ≠ 0) of the LM layer, chosen on one half, read on the other
    for half in (0, 1):
        options = [(abs(lm["directions"][n]["efficacy_half"][half][a] - 1), n, a)
                   for n in ("sae", "mean_difference", "sae_top_k")
                   if n in lm["directions"] for a, alpha in enumerate(lm["alphas"]) if alpha != 0]
        _, name, a = min(options)
        assert row["lm"]["chosen"][half] == {"layer": 2, "direction": name, "alpha": lm["alphas"][a],
                                             "alpha_vector": lm["directions"][name]["alphas_vector_units"][a]}
        assert row["lm"]["efficacy_reads"][half] == lm["directions"][name]["efficacy_half"][1 - half][a]
    assert row["lm"]["efficacy"] == pytest.approx(sum(row["lm"]["efficacy_reads"]) / 2)
    assert [c["direction"] for c in row["expert"]["chosen"]] == ["mean_difference"] * 2
    assert row["expert"]["efficacy"] == pytest.approx(1.0, abs=0.05)
    assert "| mean_difference, layer 1, α = 2 R (" in md


def test_a_reversed_direction_is_flagged(tmp_path):
    out, _ = run(tmp_path, tmp_path / "eval" / "p", sign=-1.0)
    record = json.loads((out / "dose_response.json").read_text())
    best = record["directions"]["sae"]["best"]
    assert best["alpha"] == -2.0 and best["reversed"] is True and best["request"]["alpha"] < 0
    row = next(line for line in write_layer_summary(out.parent, ["p"]).read_text().splitlines()
             if line.startswith("| p | sae | add |"))
    assert f"| -2 / {best['alpha_vector']:.4g} reversed? |" in row


def test_null_directions_follow_the_rows_covariance_and_permute_episode_labels():
    from steering_core.evaluate.metrics import null_comparison
    from steering_core.evaluate.nulls import covariance_directions, permuted_directions

    generator = torch.Generator().manual_seed(0)
    # rows vary 100x more along axis 0 than elsewhere; the two groups' means differ along axis 1 only
    rows = [torch.randn(400, 16, generator=generator) * torch.tensor([100.0] + [1.0] * 15) + 50 * k * torch.eye(16)[1]
            for k in range(2)]
    draws = covariance_directions(rows, 3.0, 32, seed=0)
    assert all(float(v.norm()) == pytest.approx(3.0, rel=1e-5) for v in draws)
    assert sum(abs(float(v[0])) / 3.0 for v in draws) / 32 > 0.9   # matched anisotropy: mostly axis 0
    assert max(abs(float(v[1])) for v in draws) / 3.0 < 0.2         # the mean difference is not in it
    constant = [torch.ones(5, 16), -torch.ones(5, 16)]  # no row differs from its task's mean (a planted concept)
    flat = torch.stack(covariance_directions(constant, 3.0, 32, seed=0))
    assert torch.isfinite(flat).all() and torch.allclose(flat.norm(dim=1), torch.full((32,), 3.0))
    assert flat.abs().argmax(dim=1).unique().numel() > 4  # isotropic draws, not one repeated axis
    # permutation: each direction is the mean difference of some relabelling keeping 2 "positive" episodes
    ep_rows = [torch.full((2, 3), float(e)) + torch.eye(3)[e % 3] for e in range(4)]  # episode e: rows of value e
    slice_rows = [torch.cat(ep_rows[:2]), torch.cat(ep_rows[2:])]
    episodes = [torch.tensor([0, 0, 1, 1]), torch.tensor([2, 2, 3, 3])]
    real = slice_rows[0].mean(0) - slice_rows[1].mean(0)
    expected = []  # in units of the real difference: a shuffle keeps its size relative to it
    for chosen in ((0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)):
        pos = torch.cat([ep_rows[e] for e in chosen]).mean(0)
        neg = torch.cat([ep_rows[e] for e in range(4) if e not in chosen]).mean(0)
        expected.append((pos - neg) / real.norm())
    shuffles = permuted_directions(slice_rows, episodes, 1.0, 8, seed=0)
    for v in shuffles:
        assert min(float((v - e).norm()) for e in expected) < 1e-5
    assert max(float(v.norm()) for v in shuffles) <= 1.0 + 1e-6  # here no split is larger than the real one
    # empirical p: (1 + #null ≥ value) / (1 + N)
    values = torch.tensor([3.0, 1.0, 2.0, 0.5])
    out = null_comparison(values, [1, 2, 3])
    assert out["p"].tolist() == pytest.approx([1 / 4, 3 / 4, 2 / 4, 4 / 4])


def test_slices_of_other_positions_are_refused(tmp_path):
    from steering_core.evaluate.positions import check_positions

    paths = slices(tmp_path / "layer02")
    assert "not checked" in check_positions(paths, "lm")
    index = {"settings": {"reduce": "token", "token_type": "instructions"}, "token_selection": {"token_type": "instructions"}}
    (tmp_path / "layer02" / "index.json").write_text(json.dumps(index))
    assert check_positions(paths, "lm") is None
    with pytest.raises(ValueError, match=r"index.json: token_type 'instructions', reduce 'token'; .* each `decision`"):
        check_positions(paths, "expert")
    for bad, found in (({"reduce": "frame"}, "reduce 'frame'"), ({"token_type": "prompt"}, "token_type 'prompt'")):
        wrong = {"settings": index["settings"] | bad, "token_selection": {"token_type": index["settings"]["token_type"]}
                 | ({"token_type": bad["token_type"]} if "token_type" in bad else {})}
        (tmp_path / "layer02" / "index.json").write_text(json.dumps(wrong))
        with pytest.raises(ValueError, match=found):
            check_positions(paths, "lm")
        m = manifest(EPISODES)
        pair = PairInputs(name="p", tasks=(POS, NEG), manifest=m, concept_map=concept_map(m),
                          split=split_episodes(m, 0.4), slices=paths)
        out = tmp_path / "eval" / "p"
        with pytest.raises(ValueError, match=found):
            evaluate_pair(pair, {"sae": planted()}, FakePolicy(WIDTH, planted(), GAP), FakeSteering,
                          load, prompts(), layer=LAYER, width=WIDTH, settings=EvaluateSettings(), output_dir=out)
        assert not out.exists()


def test_ui_artifact_inlines_the_efficacy_plot_in_a_narrow_table(tmp_path):
    from tasks.evaluate import ui_summary

    out, _ = run(tmp_path, tmp_path / "eval" / "open_vs_close")
    write_layer_summary(out.parent, ["open_vs_close"])
    text = ui_summary(out.parent)
    png = (out / "efficacy_vs_alpha.png").read_bytes()
    import base64

    assert f"data:image/png;base64,{base64.b64encode(png).decode('ascii')}" in text
    table = [line for line in text.splitlines() if line.startswith("| open_vs_close, ")]
    assert len(table) == 2 and all(line.count("|") == 6 for line in table)


def test_evaluation_identity_leaves_out_whether_the_policy_runs_compiled():
    from steering_core.evaluate import EvaluateSettings
    from tasks.evaluate import settings_inputs

    base = EvaluateSettings()
    assert settings_inputs(base.model_copy(update={"compiled": False})) == settings_inputs(base)
    assert settings_inputs(base.model_copy(update={"num_steps": 5})) != settings_inputs(base)



def fake_levels(policy: FakePolicy, vector: torch.Tensor) -> tuple[float, float]:
    """Return (m₋, m₊): each instruction's mean token embedding projected on the unit vector, the levels of the fake
    world (its steering acts on that mean)."""
    unit = vector.double() / vector.double().norm()
    positive, negative = (policy.embed[torch.tensor(ids)[INSTRUCTION[0]]].mean(0) @ unit
                          for ids in (POSITIVE_IDS, NEGATIVE_IDS))
    return float(negative), float(positive)


def test_clamp_reaches_the_other_level_at_one_where_add_needs_the_gap(tmp_path):
    """The swap moves the instruction residual by GAP = 2 R along u: add reproduces it at α = 2, clamp at α = 1 (the
    other instruction's level), whatever each frame's starting point; at α = 2 clamp overshoots to twice the swap."""
    m = manifest(EPISODES)
    pair = PairInputs(name="open_vs_close", tasks=(POS, NEG), manifest=m, concept_map=concept_map(m),
                      split=split_episodes(m, 0.4), slices=slices(tmp_path / "slices"))
    u = planted()
    policy = FakePolicy(WIDTH, u, GAP)
    directions = {"sae": u * 3.0, "mean_difference": u + 0.3 * torch.randn(WIDTH, generator=torch.Generator().manual_seed(5))}
    levels = {name: fake_levels(policy, v) for name, v in directions.items()}
    settings = EvaluateSettings(max_frames=8, noise_seeds=2, bootstrap=200, batch_size=3, device="cpu",
                                random_directions=8, permutations=4, alphas=(-1.0, 0.0, 0.5, 1.0, 2.0))
    out = tmp_path / "eval" / "open_vs_close"
    evaluate_pair(pair, directions, policy, FakeSteering, load, prompts(), layer=LAYER, width=WIDTH, settings=settings,
                  output_dir=out, levels=levels)
    record = json.loads((out / "dose_response.json").read_text())
    alphas = record["alphas"]
    assert [n for n in record["directions"] if not n.startswith(("random_", "permuted_"))] == [
        "sae", "sae:clamp", "mean_difference", "mean_difference:clamp"]
    add, clamp = record["directions"]["sae"], record["directions"]["sae:clamp"]
    assert (add["mode"], clamp["mode"], clamp["method"]) == ("add", "clamp", "sae")
    assert clamp["efficacy"][alphas.index(1.0)] == pytest.approx(1.0, abs=0.05)
    assert clamp["efficacy"][alphas.index(2.0)] == pytest.approx(2.0, abs=0.1)
    assert clamp["efficacy"][alphas.index(0.5)] == pytest.approx(0.5, abs=0.05)
    assert add["efficacy"][alphas.index(1.0)] == pytest.approx(0.5, abs=0.05)  # add: α = 1 is half the gap
    assert clamp["best"]["alpha"] == 1.0 and add["best"]["alpha"] == 2.0
    # the mean-difference direction is off u: added, only its u part moves the actions; clamped, its level still
    # reaches the other instruction's projection on it, so it does better than added at the same α
    off_add, off_clamp = record["directions"]["mean_difference"], record["directions"]["mean_difference:clamp"]
    assert off_clamp["efficacy"][alphas.index(1.0)] > off_add["efficacy"][alphas.index(1.0)]
    assert clamp["best"]["request"] == {"pair": "open_vs_close", "layer": LAYER, "direction": "sae", "alpha": 1.0,
                                        "mode": "clamp"}
    assert record["levels"] == {f"{name}:clamp": list(levels[name]) for name in directions}
    # paired difference from the reference method in the same mode, and Holm over methods x modes x α ≠ 0
    for name in ("sae", "sae:clamp"):
        versus = record["directions"][name]["best"]["vs_reference"]
        reference = record["directions"]["mean_difference" + name[3:]]["best"]["efficacy"]
        assert versus["reference"] == "mean_difference" + name[3:]
        assert versus["difference"] == pytest.approx(record["directions"][name]["best"]["efficacy"] - reference)
        assert versus["ci"][0] <= versus["difference"] <= versus["ci"][1]
        assert versus["gain"] == pytest.approx(abs(reference - 1) - abs(record["directions"][name]["best"]["efficacy"] - 1))
    p = [record["directions"][n]["p_random"][a] for n in ("sae", "sae:clamp", "mean_difference",
                                                           "mean_difference:clamp")
         for a, alpha in enumerate(alphas) if alpha != 0]
    holm_p = [record["directions"][n]["p_random_holm"][a] for n in ("sae", "sae:clamp", "mean_difference",
                                                                     "mean_difference:clamp")
              for a, alpha in enumerate(alphas) if alpha != 0]
    assert holm_p == pytest.approx(naive_holm(p))
    assert record["directions"]["sae"]["p_random_holm"][alphas.index(0.0)] is None
    md = write_layer_summary(out.parent, ["open_vs_close"]).read_text()
    assert "| open_vs_close | sae | clamp | 1 / 1 |" in md and "p random, Holm" in md


def naive_holm(p: list[float]) -> list[float]:
    """Holm's adjustment written out: sort, multiply the i-th smallest by (m − i), running maximum, cap at 1."""
    m = len(p)
    order = sorted(range(m), key=lambda i: (p[i], i))
    out, running = [0.0] * m, 0.0
    for rank, i in enumerate(order):
        running = max(running, min(1.0, (m - rank) * p[i]))
        out[i] = running
    return out


def test_holm_matches_a_hand_computation():
    from steering_core.evaluate.metrics import holm

    p = torch.tensor([0.01, 0.04, 0.03, 0.005, 0.5], dtype=torch.float64)
    # sorted: 0.005 x5 = 0.025, 0.01 x4 = 0.04, 0.03 x3 = 0.09, 0.04 x2 = 0.08 -> 0.09 (monotone), 0.5 x1 = 0.5
    assert holm(p).tolist() == pytest.approx([0.04, 0.09, 0.09, 0.025, 0.5])
    assert holm(torch.tensor([0.6, 0.7], dtype=torch.float64)).tolist() == [1.0, 1.0]


def test_clamp_with_equal_or_missing_levels_is_refused_before_anything_runs(tmp_path):
    m = manifest(EPISODES)
    pair = PairInputs(name="p", tasks=(POS, NEG), manifest=m, concept_map=concept_map(m),
                      split=split_episodes(m, 0.4), slices=slices(tmp_path / "s"))
    policy, out = FakePolicy(WIDTH, planted(), GAP), tmp_path / "eval" / "p"
    for levels, found in (({"sae": (0.5, 0.5)}, "equal levels m₋ = m₊ = 0.5"), ({}, "no clamp levels")):
        with pytest.raises(ValueError, match=f"pair 'p', layer 2, evaluate.modes clamp: method 'sae' has {found}"):
            evaluate_pair(pair, {"sae": planted()}, policy, FakeSteering, load, prompts(), layer=LAYER, width=WIDTH,
                          settings=EvaluateSettings(), output_dir=out, levels=levels)
        assert not out.exists() and policy.calls["sweep_calls"] == 0
