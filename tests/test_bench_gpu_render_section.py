"""The GPU check's render section: for real on this machine at --quick (software only, the GPU half noted), and its
table from two renderers' processes faked."""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np

REPO_ROOT = Path(__file__).resolve().parent.parent
if str(REPO_ROOT) not in sys.path:  # bench/ is a folder of scripts at the repository root, not an installed package
    sys.path.insert(0, str(REPO_ROOT))

from bench import gpu_check, gpu_harness, gpu_render_section  # noqa: E402
from steering_core.rollout.renderer import nvidia_egl_problem  # noqa: E402


def test_quick_render_section_measures_the_software_renderer_here(tmp_path):
    output = tmp_path / "check.json"
    result = gpu_check.main(["--quick", "--sections", "render", f"--cache-dir={tmp_path / 'cache'}", f"--json={output}"])
    assert result.met
    section = json.loads(output.read_text())["checks"]["sections"]["render"]
    rows = {row["measure"].split(": ")[0]: row for row in section["measures"]}
    software = rows["sim steps/s, both 256 px cameras every step, EGL in software"]
    assert "llvmpipe" in software["measure"] or "Mesa" in software["measure"]
    assert 0 < software["value"] < float(software["against"].split()[2])  # rendering costs time
    problem = nvidia_egl_problem(os.environ)
    if problem is None:
        assert "sim steps/s with both cameras, EGL on the GPU vs software" in rows
    else:
        assert f"render: EGL on the GPU not measured: {problem}." in result.notes


def fake_runs(tmp_path: Path, failing: set[str] = frozenset()):
    """Return a `run_child` answering for each renderer's process as `measure` does (frames of level 100 on the GPU,
    102 in software); the renderers in `failing` fail as run_child reports a failed process."""
    def run_child(module: str, argv: list[str], env: dict[str, str]) -> dict:
        renderer = argv[0]
        assert module == "gpu_render_section" and env["LP_NUM_THREADS"] == "1"
        assert json.loads(argv[2].removeprefix("--settings=")) == gpu_harness.QUICK.render
        if renderer in failing:
            raise RuntimeError(f"bench.gpu_render_section {renderer} failed (exit 1):\nTraceback (most recent call "
                               "last):\nRuntimeError: GPU renderer: no NVIDIA GPU visible\n")
        frames = tmp_path / f"{renderer}.npy"
        np.save(frames, np.full((2, 4, 4, 3), 100 if renderer == "gpu" else 102, dtype=np.uint8))
        name = "NVIDIA H100 80GB HBM3/PCIe/SSE2, NVIDIA Corporation" if renderer == "gpu" else "llvmpipe, Mesa"
        return {"renderer": name, "plain": 200.0, "render": 100.0 if renderer == "gpu" else 4.0, "frames": str(frames)}

    return run_child


def test_both_renderers_are_compared(tmp_path, monkeypatch):
    monkeypatch.setattr(gpu_render_section, "nvidia_egl_problem", lambda environ: None)
    monkeypatch.setattr(gpu_render_section, "run_child", fake_runs(tmp_path))
    section = gpu_render_section.render(SimpleNamespace(folder=tmp_path, sizes=gpu_harness.QUICK))
    assert section.measures == [
        {"measure": "sim steps/s, both 256 px cameras every step, EGL on the GPU: NVIDIA H100 80GB HBM3/PCIe/SSE2, "
                    "NVIDIA Corporation", "value": 100.0, "against": "no render 200.0 steps/s", "ratio": 0.5},
        {"measure": "sim steps/s, both 256 px cameras every step, EGL in software: llvmpipe, Mesa", "value": 4.0,
         "against": "no render 200.0 steps/s", "ratio": 0.02},
        {"measure": "sim steps/s with both cameras, EGL on the GPU vs software", "value": 100.0,
         "against": "software 4.00 steps/s", "ratio": 25.0},
        {"measure": "both cameras at the initial state, GPU vs software: mean |difference| (levels of 255)",
         "value": 2.0, "against": "mean level 102.0", "ratio": ""},
    ]
    assert section.comparisons == [] and len(section.notes) == 1


def test_a_renderer_whose_process_fails_is_noted(tmp_path, monkeypatch):
    monkeypatch.setattr(gpu_render_section, "nvidia_egl_problem", lambda environ: None)
    monkeypatch.setattr(gpu_render_section, "run_child", fake_runs(tmp_path, failing={"gpu"}))
    section = gpu_render_section.render(SimpleNamespace(folder=tmp_path, sizes=gpu_harness.QUICK))
    assert [row["measure"].split(":")[0] for row in section.measures] == [
        "sim steps/s, both 256 px cameras every step, EGL in software"]
    assert section.notes[0] == ("render: EGL on the GPU not measured: its process failed: RuntimeError: GPU renderer: "
                                "no NVIDIA GPU visible.")
