"""The GPU check at its --quick size on the CPU: its JSON's structure, its comparisons, and its failing exit.

No timing is asserted. On the CPU the "device" is the CPU, so float32 there must equal the float32 reference
exactly, while bfloat16 must differ from it (within its tolerance): both show the comparisons really compare.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

REPO_ROOT = Path(__file__).resolve().parent.parent
if str(REPO_ROOT) not in sys.path:  # bench/ is a folder of scripts at the repository root, not an installed package
    sys.path.insert(0, str(REPO_ROOT))

from bench import capture_input, gpu_check, gpu_harness, gpu_matmul_sections, serve_throughput  # noqa: E402
from bench.common import Result  # noqa: E402

SECTIONS = ["peak", "capture", "latency", "sweep", "server", "precision", "sae", "render"]
PRECISION_CASES = ["unsteered actions", "LM-steered actions", "expert-steered actions", "SAE-spliced actions",
                   "decision rows"]


@pytest.mark.slow
def test_quick_check_runs_every_section_and_every_comparison_passes(tmp_path):
    output = tmp_path / "check.json"
    result = gpu_check.main(["--quick", f"--cache-dir={tmp_path / 'cache'}", f"--json={output}"])
    payload = json.loads(output.read_text())
    assert Result.from_json(payload) == result
    assert payload["met"] and payload["checks"]["passed"] and payload["checks"]["failed"] == []
    assert "checkpoint" not in payload["checks"]  # recorded only for a --checkpoint run
    assert not any(note.startswith("checkpoint: ") for note in payload["notes"])
    sections = payload["checks"]["sections"]
    assert list(sections) == SECTIONS
    for name, section in sections.items():
        assert section["seconds"] > 0, name
        assert section["peak_memory"]["kind"] and section["peak_memory"]["mib"] > 0, name
        assert section["measures"] or name == "precision", name  # precision compares, it does not time
        assert all(set(row) == {"measure", "value", "against", "ratio"} for row in section["measures"]), name
    comparisons = {c["case"] + " / " + c["metric"]: c for s in sections.values() for c in s["comparisons"]}
    assert all(c["passed"] and c["error"] <= c["tolerance"] for c in comparisons.values())
    assert [c["case"] for c in sections["capture"]["comparisons"]] == ["capture rows vs seed, batch 2",
                                                                      "capture rows vs seed, batch 4"]
    assert [c["case"] for c in sections["sweep"]["comparisons"]] == ["sweep vs separate calls"]
    assert [c["case"] for c in sections["server"]["comparisons"]] == ["served steered actions vs direct infer"]
    for case in PRECISION_CASES:
        metric = "max row relative error" if case == "decision rows" else "relative error"
        # float32 on the CPU is the reference's own computation; bfloat16 rounds differently but stays close
        assert comparisons[f"float32 cpu vs float32 cpu: {case} / {metric}"]["error"] == 0
        assert 0 < comparisons[f"bfloat16 cpu vs float32 cpu: {case} / {metric}"]["error"] < 3e-2
    for stream in ("LM", "expert"):
        cosine = comparisons[f"bfloat16 cpu vs float32 cpu: effect of {stream}-steered steering / 1 - cosine"]
        assert cosine["tolerance"] == gpu_harness.TOLERANCES[torch.bfloat16]
    latency = [row["measure"] for row in sections["latency"]["measures"]]
    built = "as from_checkpoint builds it: eager"  # on the CPU; compiled denoising is CUDA's default
    assert latency == ["from_checkpoint s", f"sample_actions ms, batch 1 ({built})",
                       f"sample_actions ms, batch 4 ({built})", f"GPU kernel ms, batch 1 ({built})",
                       "sample_actions ms, batch 1, compiled denoising", "compiled batch-1 ms against the 40 ms target",
                       "compilation s (warm-up, batch 1)"]
    assert sections["latency"]["measures"][3]["value"] == "n/a (CPU)"
    assert comparisons["compiled vs eager actions, batch 1 / relative error"]["error"] < 1e-5
    assert [row["measure"].split(" SAE")[0] for row in sections["sae"]["measures"][:2]] == ["standard", "topk"]
    figures = payload["checks"]["figures"]  # what the capture-input and server benchmarks read
    assert set(figures["sample_actions_ms"]) == {"1", "4"} and figures["peak_tflops"] > 0
    assert capture_input.gpu_check_fps(output) == max(figures["capture_frames_per_s"].values())
    assert serve_throughput.gpu_inputs(output)["batch1_ms"] == figures["sample_actions_ms"]["1"]


@pytest.mark.slow
def test_a_comparison_over_its_tolerance_fails_the_check(tmp_path, monkeypatch):
    # bfloat16 against float32 is off by ~1e-3: a 1e-6 tolerance must fail those comparisons, and only those
    monkeypatch.setitem(gpu_harness.TOLERANCES, torch.bfloat16, 1e-6)
    output = tmp_path / "check.json"
    with pytest.raises(SystemExit) as exit_info:
        gpu_check.main(["--quick", "--sections", "precision", f"--cache-dir={tmp_path / 'cache'}", f"--json={output}"])
    assert exit_info.value.code == 1
    payload = json.loads(output.read_text())
    assert not payload["met"] and not payload["checks"]["passed"]
    comparisons = payload["checks"]["sections"]["precision"]["comparisons"]
    failed = {c["case"] for c in comparisons if not c["passed"]}
    assert {f"bfloat16 cpu vs float32 cpu: {case}" for case in PRECISION_CASES} <= failed
    assert all(c["passed"] for c in comparisons if c["case"].startswith("float32"))
    assert set(payload["checks"]["failed"]) == {f"{c['case']} ({c['metric']})" for c in comparisons if not c["passed"]}


def test_training_step_without_saelens_times_a_plain_torch_step(tmp_path, monkeypatch):
    monkeypatch.setattr(gpu_matmul_sections, "saelens_installed", lambda: False)
    result = gpu_check.main(["--quick", "--sections", "sae", f"--cache-dir={tmp_path}",
                             f"--json={tmp_path / 'check.json'}"])
    training = result.checks["sections"]["sae"]["measures"][-1]
    assert training["measure"].startswith("plain torch TopK step (SAELens not installed) ms")
    assert training["value"] > 0 and training["ratio"] > 0
    assert any("SAELens is not installed here" in note for note in result.notes)


def test_module_imports_neither_prefect_nor_lerobot_nor_saelens():
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(REPO_ROOT), os.environ.get("PYTHONPATH")]))}
    code = ("import sys, bench.gpu_check; "
            "print(sorted({m.split('.')[0] for m in sys.modules} & {'prefect', 'lerobot', 'sae_lens'}))")
    done = subprocess.run([sys.executable, "-c", code], cwd=REPO_ROOT, env=env, capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "[]"

