"""Steering evaluation: planted answer on a fake policy, held-out split, frames, grid, metrics, outputs, errors."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch
from helpers_evaluate import FakePolicy, FakeSteering, load, prompts
from safetensors.torch import load_file, save_file

from steering_core.data.concept_map import ConceptMap, ConceptRow
from steering_core.data.contrast import AxisSummary, ContrastManifest, Segment
from steering_core.data.split import read_split, split_episodes, write_split
from steering_core.evaluate import EvaluateSettings
from steering_core.evaluate.directions import decision_directions, random_directions
from steering_core.evaluate.frames import evenly_spaced, select_frames
from steering_core.evaluate.metrics import bootstrap_indices, dose_response_metrics
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
    """Write two concept slices as slicing does (.pt + .safetensors `residuals`); return their .pt paths."""
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for name, rows in (("pos", positive), ("neg", negative)):
        path = folder / f"{name}.pt"
        torch.save(rows, path)
        save_file({"residuals": rows}, str(path.with_suffix(".safetensors")))
        paths.append(path)
    return paths[0], paths[1]


def planted() -> torch.Tensor:
    return torch.randn(WIDTH, generator=torch.Generator().manual_seed(7))


def run(tmp_path: Path, out: Path, *, fraction: float = 0.4, **overrides) -> tuple[Path, FakePolicy]:
    m = manifest(EPISODES)
    pair = PairInputs(name="open_vs_close", tasks=(POS, NEG), manifest=m, concept_map=concept_map(m),
                      split=split_episodes(m, fraction), slices=slices(tmp_path / "slices"))
    u = planted()
    directions = {"residual_direction": u * 3.0, "mean_difference_direction": u + 0.01 * torch.ones(WIDTH)}
    directions |= {f"random_{i:02d}": v for i, v in enumerate(random_directions(WIDTH, 3.0 * float(u.norm()), 8, 0))}
    policy = FakePolicy(WIDTH, u, GAP)
    settings = EvaluateSettings(max_frames=8, noise_seeds=2, bootstrap=200, batch_size=3, device="cpu",
                                **overrides)
    evaluate_pair(pair, directions, policy, FakeSteering, load, prompts(), layer=LAYER, width=WIDTH,
                  settings=settings, output_dir=out, metadata={"policy": "fake"})
    return out, policy


def test_planted_direction_reproduces_the_swap_and_random_ones_do_not(tmp_path):
    out, policy = run(tmp_path, tmp_path / "eval" / "open_vs_close")
    record = json.loads((out / "dose_response.json").read_text())
    alphas = record["alphas"]
    at = alphas.index(2.0)
    planted_entry = record["directions"]["residual_direction"]
    assert planted_entry["efficacy"][at] == pytest.approx(1.0, abs=0.05)
    low, high = planted_entry["efficacy_ci"][at]
    assert low <= 1.0 <= high and high - low < 0.2
    assert planted_entry["best"]["alpha"] == 2.0
    assert planted_entry["cosine"][at] > 0.95
    # linear in α: half the dose, half the effect; the opposite sign moves the other way
    assert planted_entry["efficacy"][alphas.index(1.0)] == pytest.approx(0.5, abs=0.05)
    assert planted_entry["efficacy"][alphas.index(-2.0)] == pytest.approx(-1.0, abs=0.05)
    # α in vector units: α R / ||d|| with ||d|| = 3 ||u||
    norm = 3.0 * float(planted().norm())
    assert planted_entry["alphas_vector_units"][at] == pytest.approx(2.0 * NORM / norm, rel=1e-5)
    assert record["mean_residual_norm"] == pytest.approx(NORM, rel=1e-6)
    for name in record["random"]["names"]:
        assert abs(record["directions"][name]["efficacy"][at]) < 0.25
    assert planted_entry["z"][at] > 5
    assert planted_entry["efficacy"][alphas.index(0.0)] == 0.0
    # the contrast axis (state z -> action z), signed toward the positive task, integrated over the horizon
    assert planted_entry["contrast_shift"][at] == pytest.approx(record["swap"]["contrast_shift"], rel=0.1)
    # one sweep per (batch, seed) with the α = 0 entry shared: 1 + directions x nonzero alphas entries
    frames = len(record["frames"])
    batches = sum(-(-sum(f["side"] == s for f in record["frames"]) // 3) for s in ("positive", "negative"))
    assert policy.calls == {"sweep_calls": batches * 2 * 2, "sweep_entries": batches * 2 * (1 + 10 * 8),
                            "sample_actions": batches * 2}
    assert frames == 8
    tensors = load_file(out / "dose_response.safetensors")
    assert tensors["actions"].shape == (10, 9, 8, 2, 4, 7)
    assert torch.allclose(tensors["efficacy"][0], torch.tensor(planted_entry["efficacy"], dtype=torch.float32))
    for png in ("efficacy_vs_alpha.png", "shift_vs_alpha.png", "trajectory.png"):
        assert (out / png).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


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
    assert "| p | residual_direction | 2 |" in md


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


def test_metrics_against_a_hand_computed_case():
    """Two frames, one seed, horizon 1: efficacy pools inner products over frames."""
    steered = torch.zeros(1, 2, 2, 1, 1, 7, dtype=torch.float64)
    steered[0, 1, 0, 0, 0, 0] = 1.0   # frame 0 moves x by 1
    steered[0, 1, 1, 0, 0, 6] = 3.0   # frame 1 moves the gripper by 3
    swap = torch.zeros(2, 1, 1, 7, dtype=torch.float64)
    swap[0, 0, 0, 0] = 2.0            # frame 0: swap moves x by 2
    swap[1, 0, 0, 6] = 1.0            # frame 1: swap moves the gripper by 1
    out = dose_response_metrics(steered, swap, 0, 0, 1.0, bootstrap_indices(2, 50, 0))
    assert out["efficacy"][0, 1] == pytest.approx((1 * 2 + 3 * 1) / (4 + 1))
    assert out["cosine"][0, 1] == pytest.approx(1.0)
    assert out["shift"][0, 1].tolist() == pytest.approx([0.5, 0, 0, 0, 1.5])
    assert out["contrast_shift"][0, 1] == pytest.approx(0.5)
    assert out["swap_contrast_shift"] == pytest.approx(1.0)
    assert out["efficacy"][0, 0] == 0.0


def test_bad_input(tmp_path):
    with pytest.raises(ValueError, match="must include 0"):
        EvaluateSettings(alphas=(1.0, 2.0))
    with pytest.raises(ValueError, match="greater than or equal to 8"):
        EvaluateSettings(random_directions=4)
    m = manifest(EPISODES)
    pair = PairInputs(name="p", tasks=(POS, NEG), manifest=m, concept_map=concept_map(m),
                      split=split_episodes(m, 0.2), slices=slices(tmp_path / "s"))
    wrong = {"residual_direction": torch.ones(WIDTH + 1), "random_00": torch.ones(WIDTH)}
    out = tmp_path / "eval" / "p"
    with pytest.raises(ValueError, match=r"residual_direction.*\(257,\).*\(256,\)"):
        evaluate_pair(pair, wrong, FakePolicy(WIDTH, planted(), GAP), FakeSteering, load, prompts(), layer=LAYER,
                      width=WIDTH, settings=EvaluateSettings(), output_dir=out)
    assert not out.exists()


def test_model_checks_name_the_problem(tmp_path):
    from steering_core.capture import CaptureSettings
    from steering_core.evaluate.run import check_model
    from steering_core.pi05 import PromptFormat
    from steering_core.synthetic.pi05 import tiny_arch

    arch = tiny_arch()
    model = CaptureSettings(checkpoint_path=tmp_path / "missing", tokenizer_path=tmp_path / "tok", layers=(1,), arch=arch)
    with pytest.raises(FileNotFoundError, match="missing: policy checkpoint not found"):
        check_model(model, 1)
    (tmp_path / "ckpt").mkdir()
    model = model.model_copy(update={"checkpoint_path": tmp_path / "ckpt"})
    with pytest.raises(ValueError, match=rf"layer {arch.depth} is not a layer of the policy: it has {arch.depth}"):
        check_model(model, arch.depth)
    with pytest.raises(ValueError, match="needs the libero format"):
        check_model(model.model_copy(update={"prompt_format": PromptFormat.DISCRETE_STATE}), 1)
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
    directions = decision_directions(pair.slices, random_count=8, seed=0)
    policy = FakePolicy(EXPERT_WIDTH, u, GAP, stream="expert")
    settings = EvaluateSettings(max_frames=8, noise_seeds=2, bootstrap=200, batch_size=3, device="cpu")
    evaluate_pair(pair, directions, policy, FakeSteering, load, prompts(), layer=EXPERT_LAYER, width=width,
                  settings=settings, output_dir=out, metadata={"policy": "fake"}, stream="expert")
    return out, policy


def test_planted_expert_direction_reproduces_the_swap_and_random_ones_do_not(tmp_path):
    out, policy = run_expert(tmp_path, tmp_path / "eval" / "expert_layer01" / "open_vs_close")
    record = json.loads((out / "dose_response.json").read_text())
    assert record["stream"] == "expert" and record["layer"] == EXPERT_LAYER
    assert record["alpha_units"].startswith("mean decision-residual norm at the expert layer / ||d||")
    assert list(record["directions"]) == ["decision_mean_difference"] + [f"random_{i:02d}" for i in range(8)]
    alphas = record["alphas"]
    at = alphas.index(2.0)  # the swap moves the expert residual by GAP = 2 R along the planted direction
    entry = record["directions"]["decision_mean_difference"]
    assert entry["efficacy"][at] == pytest.approx(1.0, abs=0.05)
    low, high = entry["efficacy_ci"][at]
    assert low <= 1.0 <= high and high - low < 0.2
    assert entry["best"]["alpha"] == 2.0 and entry["z"][at] > 5
    assert entry["efficacy"][alphas.index(-2.0)] == pytest.approx(-1.0, abs=0.05)
    for name in record["random"]["names"]:
        assert abs(record["directions"][name]["efficacy"][at]) < 0.25
    # α unit: the decision rows' mean norm; in vector units α R / ||d|| with d = 2 HALF_GAP û
    assert record["mean_residual_norm"] == pytest.approx(NORM, rel=1e-5)
    assert record["direction_norms"]["decision_mean_difference"] == pytest.approx(2 * HALF_GAP, rel=1e-5)
    assert entry["alphas_vector_units"][at] == pytest.approx(2.0 * NORM / (2 * HALF_GAP), rel=1e-5)
    # random directions of equal norm, in expert width; the direction itself is kept with the outputs
    norms = record["direction_norms"]
    assert all(norms[n] == pytest.approx(2 * HALF_GAP, rel=1e-5) for n in record["random"]["names"])
    tensors = load_file(out / "dose_response.safetensors")
    unit = expert_planted().double() / expert_planted().double().norm()
    assert tensors["directions"].shape == (9, EXPERT_WIDTH)
    torch.testing.assert_close(tensors["directions"][0].double(), 2 * HALF_GAP * unit, rtol=0, atol=1e-5)
    # one sweep per (batch, seed), α = 0 shared: 1 + 9 directions x 8 nonzero α entries
    batches = sum(-(-sum(f["side"] == s for f in record["frames"]) // 3) for s in ("positive", "negative"))
    assert policy.calls == {"sweep_calls": batches * 2 * 2, "sweep_entries": batches * 2 * (1 + 9 * 8),
                            "sample_actions": batches * 2}
    md = write_layer_summary(out.parent, ["open_vs_close"]).read_text()
    assert md.startswith("# Steering evaluation, expert_layer01") and "| open_vs_close | decision_mean_difference | 2 |" in md


def test_expert_outputs_are_byte_identical_and_the_width_is_checked(tmp_path):
    first, _ = run_expert(tmp_path, tmp_path / "a" / "p")
    second, _ = run_expert(tmp_path, tmp_path / "b" / "p")
    names = sorted(p.name for p in first.iterdir())
    assert names == sorted(p.name for p in second.iterdir()) and "efficacy_vs_alpha.png" in names
    for name in names:
        assert (first / name).read_bytes() == (second / name).read_bytes(), name
    out = tmp_path / "c" / "p"
    with pytest.raises(ValueError, match=r"decision_mean_difference.*\(128,\).*action expert.s residual width \(129,\)"):
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
    expert = json.loads((root / "expert_layer01" / "open_vs_close" / "dose_response.json").read_text())
    # the LM side: of residual/mean-difference, the one whose best efficacy is closest to 1
    best = min(("residual_direction", "mean_difference_direction"),
               key=lambda n: abs(lm["directions"][n]["best"]["efficacy"] - 1))
    assert (row["lm"]["layer"], row["lm"]["direction"]) == (2, best)
    assert row["lm"]["efficacy"] == lm["directions"][best]["best"]["efficacy"]
    assert row["expert"] == {"layer": 1, "direction": "decision_mean_difference",
                             **expert["directions"]["decision_mean_difference"]["best"]}
    assert f"| open_vs_close | {best}, layer 2, α = 2 |" in md
    assert "| decision_mean_difference, layer 1, α = 2 |" in md
