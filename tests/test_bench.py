"""Smoke tests of the benchmarks: each runs at its --quick size and its correctness checks hold.

No timing is asserted anywhere: the numbers of a quick run mean nothing. What is asserted is that each
benchmark's baseline computes the same thing as our code (same residual rows, same concept ranges, same
latent means), that the seed's inference-call model does the work it claims, that the FLOP model gives
hand-computed answers, and that the report renders.
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

REPO_ROOT = Path(__file__).resolve().parent.parent
if str(REPO_ROOT) not in sys.path:  # bench/ is a folder of scripts at the repository root, not an installed package
    sys.path.insert(0, str(REPO_ROOT))

from bench import (  # noqa: E402
    capture_input,
    capture_throughput,
    cli_startup,
    concept_map_speed,
    evaluate_cost,
    policy_latency,
    policy_sweep,
    real_size,
    rollout_grid,
    rollout_throughput,
    run_all,
    sae_encoding,
    sae_training,
    serve_latency,
    serve_throughput,
    slicing_memory,
)
from bench.common import Result  # noqa: E402
from bench.seed_pi05 import ACTION_DIM, ACTION_HORIZON, DENOISE_STEPS, SeedPi05  # noqa: E402
from steering_core.pi05 import Pi05Arch  # noqa: E402
from steering_core.synthetic.pi05 import tiny_arch, write_pi05_checkpoint  # noqa: E402


@pytest.fixture(scope="module")
def cache(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("bench-cache")


@pytest.fixture(scope="module")
def refresh_run(tmp_path_factory, prefect_server):
    """Start the refresh benchmark's quick run in its own process at the module's first slow test (which asks for
    it), so its two pipeline runs overlap the other benchmarks; the last test waits for it. The fast loop, which
    leaves the slow tests out, never starts it."""
    folder = tmp_path_factory.mktemp("bench-refresh")
    output = folder / "result.json"
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(REPO_ROOT), os.environ.get("PYTHONPATH")])),
           "PREFECT_API_URL": prefect_server}  # the session's server: no embedded server to start under load
    process = subprocess.Popen(
        [sys.executable, "-m", "bench.incremental_refresh", "--quick",
         f"--cache-dir={folder}", f"--json={output}"],
        cwd=REPO_ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
    )
    yield process, output
    if process.poll() is None:
        process.kill()
        process.communicate()


def run_quick(module, cache: Path, tmp_path: Path) -> Result:
    """Run a benchmark's main at --quick size; check its JSON round trip; return the result."""
    output = tmp_path / "result.json"
    result = module.main(["--quick", f"--cache-dir={cache}", f"--json={output}"])
    assert Result.from_json(json.loads(output.read_text())) == result
    assert result.table and math.isfinite(result.ratio) and result.ratio > 0
    assert result.command.startswith("uv run python -m bench.") and "--quick" in result.command
    return result


@pytest.mark.slow
def test_capture_baseline_captures_the_same_rows(cache, tmp_path, refresh_run):
    result = run_quick(capture_throughput, cache, tmp_path)
    assert result.checks["max_abs_difference"] < 1e-4
    cases = [row["case"] for row in result.table]
    assert cases == ["measured cpu, layer 2", "measured cpu, layers 1,2 (seed: 2 x its measured pass)",
                     "real pi0.5, layer 12 (analytic)", "real pi0.5, layers 4,8,12 (analytic)"]


@pytest.mark.slow
def test_capture_input_measures_every_loader_against_the_model(cache, tmp_path):
    result = run_quick(capture_input, cache, tmp_path)
    cases = [row["case"].split(" (")[0] for row in result.table]
    assert cases == ["old: decode + resize in 1 worker", "decode, 1 worker", "decode, 2 workers",
                     "decode + slots on cpu, default", "projected: 16-core machine, default 8 workers", "model"]
    rates = {case: row["frames/s"] for case, row in zip(cases, result.table)}
    efficiency = rates["decode, 2 workers"] / (2 * rates["decode, 1 worker"])
    assert result.checks["efficiency"] == pytest.approx(efficiency)
    assert rates["projected: 16-core machine, default 8 workers"] == pytest.approx(rates["decode, 1 worker"] * 8 * efficiency)
    assert result.ratio == pytest.approx(rates["projected: 16-core machine, default 8 workers"] / rates["model"])


def test_capture_input_and_the_study_model_read_a_gpu_checks_figures(tmp_path):
    check = tmp_path / "gpu_check.json"
    figures = {"peak_tflops": 790.0, "capture_frames_per_s": {"32": 240.0, "128": 236.0},
               "sample_actions_ms": {"1": 38.0, "4": 41.0}}
    check.write_text(json.dumps({"checks": {"figures": figures}}))
    assert capture_input.gpu_check_fps(check) == 240.0  # the fastest batch
    model = serve_throughput.gpu_inputs(check)
    assert (model["peak_tflops"], model["batch1_ms"]) == (790.0, 38.0)
    check.write_text(json.dumps({"checks": {"figures": {"peak_tflops": 790.0}}}))
    with pytest.raises(ValueError, match=r"gpu_check.json: no figures \['capture_frames_per_s'\] under checks.figures"):
        capture_input.gpu_check_fps(check)


@pytest.mark.slow
def test_concept_map_baseline_finds_the_same_ranges(cache, tmp_path):
    result = run_quick(concept_map_speed, cache, tmp_path)
    assert result.checks == {"same_mapping": True, "frames": 160}


@pytest.mark.slow
def test_slicing_benchmark_reports_every_size(cache, tmp_path):
    result = run_quick(slicing_memory, cache, tmp_path)
    assert [row["case"] for row in result.table] == ["1x run, fixed pair", "1x run, every row sliced",
                                                     "10x run, fixed pair"]
    assert [row["episodes"] for row in result.table] == [4, 4, 40]
    assert result.checks["peak_rss_spread"] >= 1.0


@pytest.mark.slow
def test_sae_baseline_gets_the_same_latent_means(cache, tmp_path):
    result = run_quick(sae_encoding, cache, tmp_path)
    assert result.checks["latent_mean_max_abs_difference"] < 1e-5
    assert result.checks["seed_peak_mib"] > 0 and result.checks["ours_peak_mib"] > 0


@pytest.mark.slow
def test_sae_training_benchmark_times_the_step_the_bound_and_the_loader(cache, tmp_path):
    result = run_quick(sae_training, cache, tmp_path)
    assert [row["method"].split(":")[0].split(",")[0] for row in result.table] == [
        "ours", "torch.matmul", "RowSource.shuffled alone (the same stream)"]
    assert all(row["rows/s"] > 0 for row in result.table) and result.ratio > 0
    assert result.checks["loader_over_ours"] == result.table[2]["rows/s"] / result.table[0]["rows/s"]


@pytest.mark.slow
def test_real_size_section_runs_at_tiny_size(cache, tmp_path):
    result = run_quick(real_size, cache, tmp_path)
    measures = [row["measure"] for row in result.table]
    assert measures[:6] == ["load time s", "loaded parameter MiB (float32)", "RSS before load MiB (imports)",
                            "peak RSS after load MiB", "peak RSS / loaded bytes", "(peak - before) / loaded bytes"]
    values = {row["measure"]: row["value"] for row in result.table}
    # the selected-rows call does less work than the full one by the analytic count
    assert 0 < values["capture's call / every row, analytic FLOPs"] < 1
    assert "Opt-in" in real_size.__doc__ and "real_size" in run_all.OPT_IN and "real_size" not in run_all.BENCHMARKS


@pytest.mark.slow
def test_evaluation_sweep_gives_the_naive_loops_actions(cache, tmp_path):
    result = run_quick(evaluate_cost, cache, tmp_path)
    assert result.checks["max_abs_difference"] < 1e-4
    assert result.checks["naive_calls"] == 2 * 1 * (4 * 3 + 1)  # frames x seeds x (directions x alphas + swap)
    assert [row["case"] for row in result.table] == ["measured cpu, layer 2",
                                                     "real pi0.5, layer 12, one pair (analytic)",
                                                     "methods: 4 x 2 modes + null vs 1 method + null, layer 2"]
    assert result.checks["methods_ratio"] > 0


def test_evaluation_flop_model_known_answers():
    from steering_core.evaluate import EvaluateSettings

    real = Pi05Arch()
    parts = evaluate_cost.call_flops(real)
    assert parts["vision"] + real.depth * parts["layer"] + parts["expert"] == pytest.approx(parts["full"])
    # 2 frames x 1 seed; 1 direction x 2 nonzero alphas in 2 calls of one entry each (the first also runs alpha 0)
    settings = EvaluateSettings(alphas=(-1.0, 0.0, 1.0), max_frames=2, noise_seeds=1, entries_per_call=1)
    flops = evaluate_cost.pair_layer_flops(real, 12, settings, directions=1)
    shared = parts["vision"] + 13 * parts["layer"]
    per_entry = 5 * parts["layer"] + parts["expert"]
    assert flops["ours"] == pytest.approx(2 * (2 * shared + 3 * per_entry + parts["full"]))
    assert flops["naive"] == pytest.approx(2 * 4 * parts["full"])
    assert evaluate_cost.h100_seconds(flops["ours"]) == pytest.approx(flops["ours"] / (0.4 * 989e12))


@pytest.mark.slow
def test_policy_sweep_equals_separate_calls(cache, tmp_path):
    result = run_quick(policy_sweep, cache, tmp_path)
    assert result.checks["max_abs_difference"] < 1e-5 < result.checks["alpha_spread"]
    assert [row["case"] for row in result.table] == ["measured cpu, lm layer 1, 8 alphas",
                                                     "real pi0.5, lm layer 12 (analytic)",
                                                     "real pi0.5, expert stream (analytic)"]


@pytest.mark.slow
def test_policy_latency_compiled_gives_the_eager_actions(cache, tmp_path):
    result = run_quick(policy_latency, cache, tmp_path)
    assert result.checks["max_abs_difference"] < 1e-4
    assert [row["batch"] for row in result.table] == list(policy_latency.QUICK["batches"])
    assert all(row["warm-up s (compile)"] > 0 and row["compiled ms"] > 0 for row in result.table)


def test_policy_sweep_flop_model():
    real = Pi05Arch()
    separate = policy_sweep.separate_flops(real, 8, 16)
    # 8 alphas at layer 12 share SigLIP and layers 0..12: about a third of eight full calls
    assert 0.3 < policy_sweep.sweep_flops(real, 8, 16, 12) / separate < 0.4
    # one entry shares nothing, whatever the layer
    assert policy_sweep.sweep_flops(real, 1, 16, 12) == pytest.approx(policy_sweep.separate_flops(real, 1, 16))
    # steering the expert only shares the whole prefix: 1 prefix + 8 expert loops
    expert_loop = policy_sweep.STEPS * capture_throughput.expert_step_flops(real, 2 * 256 + 16)
    one_call = policy_sweep.separate_flops(real, 1, 16)
    assert policy_sweep.sweep_flops(real, 8, 16, None) == pytest.approx(one_call + 7 * expert_loop)


@pytest.mark.slow
def test_cli_startup_measures_light_commands_without_heavy_libraries(cache, tmp_path):
    result = run_quick(cli_startup, cache, tmp_path)
    heavy = result.checks["heavy"]
    assert heavy["latent-steering --help"] == heavy["latent-steering filter (2 of 4 files)"] == "none"
    assert heavy["latent-steering steer --help (needs torch)"] == "torch"  # the check can tell them apart
    assert [row["command"] for row in result.table][-1] == "python -c pass (baseline)"
    assert (cache / "cli-startup-filtered" / "selection.json").is_file()  # filter did its work

@pytest.mark.slow
def test_served_actions_equal_direct_infer(cache, tmp_path):
    result = run_quick(serve_latency, cache, tmp_path)
    assert result.checks["served_equals_direct"] is True
    calls = [row["call"] for row in result.table]
    assert calls[:5] == ["tiny model: direct", "tiny model: server", "tiny model: direct steered",
                         "tiny model: server steered", "server, policy doing no work (protocol alone)"]
    assert all(row["calls"] == serve_latency.QUICK["rounds"] for row in result.table[:5])


@pytest.mark.slow
def test_rollout_loops_execute_the_same_actions(cache, tmp_path, prefect_server, monkeypatch):
    monkeypatch.setenv("PREFECT_API_URL", prefect_server)  # phases 1-3 of the demo run on the session's server
    result = run_quick(rollout_throughput, cache, tmp_path)
    checks = result.checks
    assert checks["same_actions_openpi_loop"] and checks["same_actions_served"] and checks["same_call_actions"]
    assert checks["same_actions_recorded"]  # a recorded episode renders every step and acts the same
    assert (checks["episode_steps"], checks["policy_calls"]) == (rollout_throughput.QUICK["episode_steps"], 2)
    # the demo's 7 cells x 1 episode on 1 and on 2 simulation workers, the policy loaded once in each run
    assert checks["phase_episodes"] == {"1": 7, "2": 7} and checks["policy_loads"] == {"1": 1, "2": 1}
    # 3 episodes on 2 envs in lockstep end as on one env, first chunks equal, sharing calls of 2 rows; 6 steps each
    assert checks["same_episodes_lockstep"] and checks["lockstep_batch_rows"] == 2
    assert checks["lockstep_episode_steps"] == [rollout_throughput.QUICK["lockstep_steps"]] * 3
    assert [row["measure"][:2] for row in result.table] == ["1.", "1.", "2.", "2.", "3.", "3.", "4.", "4.", "5.",
                                                             "6.", "6."]


def test_seed_model_runs_a_whole_inference_call(tmp_path):
    arch = tiny_arch()
    checkpoint = write_pi05_checkpoint(tmp_path / "ckpt", arch)
    model = SeedPi05.from_checkpoint(checkpoint, arch, torch.device("cpu"))
    calls: dict[str, list] = {"prefix": [], "expert": []}
    for layer in model.prefix.layers:
        layer.register_forward_pre_hook(
            lambda _m, args, kwargs: calls["prefix"].append((args[0].shape, kwargs["attention_mask"].shape)),
            with_kwargs=True,
        )
    for layer in model.gemma_expert.model.layers:
        layer.register_forward_pre_hook(lambda _m, args: calls["expert"].append(args[0].shape))
    batch, side, slots = 2, arch.image_size, 200
    images = [torch.zeros(batch, 3, side, side) for _ in range(3)]
    present, absent = torch.ones(batch, dtype=torch.bool), torch.zeros(batch, dtype=torch.bool)
    masks = [present, present, absent]
    tokens = torch.zeros(batch, slots, dtype=torch.long)
    token_mask = torch.zeros(batch, slots, dtype=torch.bool)
    token_mask[:, :5] = True
    actions = model.sample_actions(images, masks, tokens, token_mask)

    full = 3 * arch.tokens_per_image + slots  # every camera slot and every language slot, padding included
    assert actions.shape == (batch, ACTION_HORIZON, ACTION_DIM) and torch.isfinite(actions).all()
    assert calls["prefix"] == [((batch, full, arch.width), (batch, 1, full, full))] * arch.depth
    assert calls["expert"] == [(batch, ACTION_HORIZON, arch.width // 2)] * (arch.depth * DENOISE_STEPS)


def test_flop_model_known_answers():
    arch = Pi05Arch(width=64, depth=4, mlp_dim=128, num_heads=8, num_kv_heads=1, head_dim=16, vocab_size=512)
    # per token: q 64x128, k and v 64x16 each, o 128x64, MLP 3 x 64x128 = 43008 multiply-adds; 10 tokens, x2
    # attention: (q k^T and p v) x 10 queries x 20 keys x 128 query width x 2 = 102400
    assert capture_throughput.decoder_layer_flops(arch, 10, 20) == 2 * 10 * 43008 + 102400
    real = Pi05Arch()
    ours = capture_throughput.ours_flops(real, 12, 16)
    seed = capture_throughput.seed_flops(real, 1)
    assert capture_throughput.seed_flops(real, 3) == pytest.approx(3 * seed)
    # ours runs 2 of 3 cameras and 13 of 18 layers over fewer tokens: well under half the prefix
    assert 2.0 < seed / ours < 3.0
    assert capture_throughput.h100_frames_per_second(ours) == pytest.approx(0.4 * 989e12 / ours)


def test_policy_flop_model_and_the_study_model_known_answers():
    real = Pi05Arch()
    sample = capture_throughput.sample_flops(real, 16)
    # every layer and ten expert steps: more than capture's prefix to layer 12; the seed's call (3 cameras, 200
    # language slots) about twice as much
    assert sample > capture_throughput.ours_flops(real, 12, 16)
    assert 1.5 < capture_throughput.seed_flops(real, 1) / sample < 2.5
    gpu = {"peak_tflops": 800.0, "batch1_ms": 100.0, "source": "hand"}
    rows = {row["quantity"].split(" (")[0]: row["value"] for row in serve_throughput.grid_model(gpu)}
    row_s = sample / (0.4 * 800e12)
    assert rows["policy rows"] == 2000 * 60  # 300 steps replanned every 5
    assert rows["GPU s per call of rows_per_call rows"] == pytest.approx(max(0.1, 16 * row_s))
    assert rows["GPU minutes"] == pytest.approx(7500 * max(0.1, 16 * row_s) / 60)
    assert rows["simulator minutes"] == pytest.approx(2000 * (310 / 93.7 + 60 * 0.216) / 16 / 60)
    # workers sharing the server: each waits one call per replan of its 8 lockstep envs, or the GPU is the limit
    wait_min = 2000 * 60 * max(0.1, 16 * row_s) / (16 * 8) / 60
    assert rows["study minutes"] == pytest.approx(rows["GPU minutes"] + rows["simulator minutes"])
    assert rows["phase minutes"] == pytest.approx(max(rows["GPU minutes"], rows["simulator minutes"] + wait_min))
    slow_sim = {"steps_per_s": 10.0, "render_s": 1.0, "source": "hand"}
    assert serve_throughput.grid_model(gpu, sim=slow_sim)[3]["value"] == pytest.approx(2000 * (31 + 60) / 16 / 60)


def test_the_method_grid_counts_its_cells_from_the_settings_and_models_their_time():
    # per side: α = 0, the swap, and at each of 3 pushes M x modes steered cells, 4 random directions, the wrong
    # concept; 50 episodes per cell
    assert rollout_grid.grid_size(("sae",), ("add",)) == (40, 2000)  # section 16's study
    assert rollout_grid.grid_size(("sae", "mean_difference"), ("add", "clamp")) == (2 * (2 + 3 * 9), 2900)
    gpu = {"peak_tflops": 800.0, "batch1_ms": 100.0, "source": "hand"}
    rows = rollout_grid.method_grid(gpu)
    assert [(row["methods"], row["modes"], row["episodes"]) for row in rows][-2:] == [
        (4, "add", 2 * (2 + 3 * 9) * 50), (4, "add + clamp", 2 * (2 + 3 * 13) * 50)]
    study = {row["quantity"].split(" (")[0]: row["value"] for row in serve_throughput.grid_model(gpu, 4100)}
    assert rows[-1]["total min (no overlap)"] == study["study minutes"]
    assert rows[0]["GPU min"] == serve_throughput.grid_model(gpu)[2]["value"]  # one method, add: the 2,000 episodes


@pytest.mark.slow
def test_batched_server_answers_each_client_as_alone(cache, tmp_path):
    result = run_quick(serve_throughput, cache, tmp_path)
    assert result.checks["same_as_alone"] is True
    assert [(row["clients"], row["batching"]) for row in result.table] == [(1, "off"), (1, "on"), (8, "off"),
                                                                           (8, "on")]
    assert all(row["rows per call"] == 1 for row in result.table if row["batching"] == "off")
    assert result.checks["rows_per_call_8"] > 1  # eight clients in a closed loop share calls


def test_report_renders_summary_and_sections():
    results = [
        ("concept_map_speed", Result("concept_map", "2. Concept map", "uv run python -m bench.concept_map_speed",
                                     "10 frames/s", "1 frames/s", 10.0, ">= 100x", False,
                                     [{"method": "ours", "seconds": 0.5}], ["a note"]), 12.0),
    ]
    text = run_all.render(results, {"date": "today", "cpu": "test cpu"}, 90.0, "uv run python -m bench.run_all")
    assert "| 2. Concept map | 10 frames/s | 1 frames/s | 10.00x | >= 100x | **no** | 12 s | " \
           "`uv run python -m bench.concept_map_speed` |" in text
    assert "## 2. Concept map" in text and "| ours | 0.5 |" in text and "- a note" in text
    assert "| cpu | test cpu |" in text and "took 1.5 min" in text
    assert "found by binary search over the" in text  # the module docstring explains the method
    assert "[--device cuda]" not in text  # but its usage line stays out


@pytest.mark.slow
def test_refresh_captures_only_the_added_file(refresh_run):
    process, output = refresh_run
    log, _ = process.communicate(timeout=600)
    assert process.returncode == 0, log[-4000:]
    result = Result.from_json(json.loads(output.read_text()))
    assert result.name == "refresh" and len(result.table) == 2 and result.ratio > 0
    assert result.checks["refresh_ran"] and result.checks["old_shards_untouched"]
    assert result.checks["shards_added"] == 2 * 2  # the added file's 2 episodes, 2 layers
    assert result.checks["changes"].startswith("1 added (KITCHEN_SCENE30_open_the_top_drawer")
    # evaluation counts: the added file's pair is evaluated again at every layer, the other pair read from the cache
    assert result.checks["evaluations"] == 2 * result.checks["evaluations_redone"] > 0
