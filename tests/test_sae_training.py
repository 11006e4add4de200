"""train_sae: a planted dictionary is recovered, SAELens reads our folder, a killed run resumes to the same bytes."""

from __future__ import annotations

import json
import logging
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
from test_sae_rows import write_nan_row

from steering_core.sae.formats import CFG_FILE, SPARSITY_FILE, WEIGHTS_FILE
from steering_core.sae.model import load_sae
from steering_core.sae.training.rows import RowSource
from steering_core.sae.training.settings import TrainSettings
from steering_core.sae.training.trainer import CHECKPOINTS_DIR, TRAINING_FILE, read_training_record, train_sae
from steering_core.synthetic.residual_run import LAYER, write_rows_run

D_IN, DIRECTIONS, ACTIVE = 32, 64, 3
PLANTED = TrainSettings(d_sae=128, k=4, lr=3e-3, batch_size=256, training_rows=256 * 1200, buffer_rows=4096,
                        checkpoints=0, device="cpu")
SAE_FILES = (CFG_FILE, WEIGHTS_FILE, SPARSITY_FILE)


@pytest.fixture(scope="module", autouse=True)
def one_thread():
    """Tiny matrices: a second thread only adds synchronisation on a shared machine (and both runs of the
    kill test must use the same count for the same bytes)."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def planted_rows(n: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Return (directions (DIRECTIONS, D_IN) unit rows, rows (n, D_IN)): each row ACTIVE directions with
    coefficients in [0.5, 2.5]."""
    generator = torch.Generator().manual_seed(seed)
    directions = torch.nn.functional.normalize(torch.randn(DIRECTIONS, D_IN, generator=generator), dim=1)
    chosen = torch.rand(n, DIRECTIONS, generator=generator).argsort(dim=1)[:, :ACTIVE]
    weights = torch.rand(n, ACTIVE, generator=generator) * 2 + 0.5
    return directions, torch.zeros(n, DIRECTIONS).scatter(1, chosen, weights) @ directions


@pytest.fixture(scope="module")
def planted(tmp_path_factory):
    """A planted run, the SAE trained on its episodes 0-6, and the held-out rows of episode 7."""
    folder = tmp_path_factory.mktemp("planted")
    directions, rows = planted_rows(16_000, seed=0)
    write_rows_run(folder / "run", rows, episodes=8)
    source = RowSource(folder / "run", LAYER, exclude=[7])
    start = time.perf_counter()
    out = train_sae(source, folder / "sae", PLANTED, layer=LAYER)
    return {"out": out, "source": source, "directions": directions, "held_out": rows[14_000:],
            "seconds": time.perf_counter() - start}


def test_a_planted_dictionary_is_recovered_with_a_low_fvu(planted):
    sae = load_sae(planted["out"])
    decoder = torch.nn.functional.normalize(sae.W_dec, dim=1)
    best = (planted["directions"] @ decoder.T).max(dim=1).values  # each true direction's closest decoder row
    assert best.min() >= 0.9, best.sort().values[:5]
    x = planted["held_out"]
    latents, norm = sae.encode_with_norm(x)
    fvu = (x - sae.decode(latents, norm)).pow(2).sum() / (x - x.mean(0)).pow(2).sum()
    assert fvu < 0.1
    assert (latents != 0).sum(dim=1).max() <= PLANTED.k


def test_saelens_loads_our_folder_and_agrees_with_load_sae(planted):
    from sae_lens import SAE

    theirs, ours = SAE.load_from_disk(planted["out"]), load_sae(planted["out"])
    x = planted["held_out"][:500]
    with torch.no_grad():
        their_latents = theirs.encode(x)
        latents, norm = ours.encode_with_norm(x)
        assert torch.allclose(their_latents, latents, atol=1e-5, rtol=0)
        assert torch.allclose(theirs.decode(their_latents), ours.decode(latents, norm), atol=1e-5, rtol=0)
    metadata = json.loads((planted["out"] / CFG_FILE).read_text())["metadata"]
    assert (metadata["hook_name"], metadata["hook_layer"], metadata["model_name"]) == (
        f"blocks.{LAYER}.hook_resid_post", LAYER, "pi05")


def test_the_record_names_rows_and_settings_and_a_finished_folder_is_reused(planted, tmp_path):
    out, source = planted["out"], planted["source"]
    record = read_training_record(out)
    assert record["source"]["identity"] == source.identity() and record["source"]["episodes"] == list(range(7))
    assert record["settings"] == PLANTED.model_dump(mode="json")
    assert record["metrics"]["rows_seen"] == PLANTED.training_rows and record["metrics"]["l0"] <= PLANTED.k
    assert sorted(p.name for p in out.iterdir()) == sorted([*SAE_FILES, TRAINING_FILE])  # checkpoints removed
    stamps = {name: (out / name).stat().st_mtime_ns for name in SAE_FILES}
    start = time.perf_counter()
    assert train_sae(source, out, PLANTED, layer=LAYER) == out
    assert time.perf_counter() - start < 1.0 and stamps == {n: (out / n).stat().st_mtime_ns for n in SAE_FILES}
    # other settings (a refresh's new rows alike): the folder is trained again, in place
    stale = shutil.copytree(out, tmp_path / "stale")
    other = PLANTED.model_copy(update={"seed": 1, "training_rows": PLANTED.batch_size * 20})
    assert train_sae(source, stale, other, layer=LAYER) == stale
    assert read_training_record(stale)["settings"] == other.model_dump(mode="json")
    assert (stale / WEIGHTS_FILE).read_bytes() != (out / WEIGHTS_FILE).read_bytes()


KILLED_CHILD = """
import sys, time, torch
from steering_core.sae.training.rows import RowSource
from steering_core.synthetic.residual_run import LAYER, write_rows_run
from steering_core.sae.training.settings import TrainSettings
from steering_core.sae.training.trainer import train_sae
torch.set_num_threads(1)
settings = TrainSettings.model_validate_json(sys.argv[3])
slow = lambda done, total: time.sleep(0.003)  # room to be killed between checkpoints; the bytes do not change
train_sae(RowSource(sys.argv[1], int(sys.argv[2])), sys.argv[4], settings, layer=int(sys.argv[2]), progress=slow)
"""
RESUMED = TrainSettings(architecture="batchtopk", d_sae=48, k=3, lr=2e-3, batch_size=64, training_rows=64 * 500,
                        buffer_rows=1024, checkpoints=4, dead_feature_window=50, feature_sampling_window=60,
                        device="cpu")  # firing counts reset every 60 steps: a resume must keep their phase


@pytest.mark.slow
def test_a_run_killed_after_a_checkpoint_resumes_to_the_bytes_of_an_uninterrupted_one(tmp_path, caplog):
    _, rows = planted_rows(3000, seed=1)
    write_rows_run(tmp_path / "run", rows[:, :16], episodes=3)
    source = RowSource(tmp_path / "run", LAYER)
    killed = tmp_path / "killed"
    child = subprocess.Popen([sys.executable, "-c", KILLED_CHILD, str(tmp_path / "run"), str(LAYER),
                              RESUMED.model_dump_json(), str(killed)], cwd=Path(__file__).resolve().parents[1],
                             stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        deadline = time.monotonic() + 240
        while not list((killed / CHECKPOINTS_DIR).glob("[0-9]*/checkpoint.json")):
            assert child.poll() is None, child.stderr.read().decode()[-2000:]
            assert time.monotonic() < deadline, "no checkpoint within 240 s"
            time.sleep(0.02)
        os.kill(child.pid, signal.SIGKILL)
    finally:
        child.kill()
        child.wait()
        child.stderr.close()
    assert not (killed / TRAINING_FILE).exists()
    with caplog.at_level(logging.INFO, logger="steering_core.sae.training.trainer"):
        train_sae(source, killed, RESUMED, layer=LAYER)
    resumed = [r.getMessage() for r in caplog.records if r.getMessage().startswith("resuming from")]
    assert resumed and int(resumed[0].split("(")[1].split()[0]) > 0, resumed
    uninterrupted = train_sae(source, tmp_path / "uninterrupted", RESUMED, layer=LAYER)
    for name in [*SAE_FILES, TRAINING_FILE]:  # training.json too: the record holds nothing about the kill
        assert (killed / name).read_bytes() == (uninterrupted / name).read_bytes(), name
    assert sorted(p.name for p in killed.iterdir()) == sorted([*SAE_FILES, TRAINING_FILE])  # no staging left
    # cfg.json's keys are sorted: SAELens's own order follows a set, so it changes with each process's hash seed
    assert list(json.loads((killed / CFG_FILE).read_text())) == sorted(json.loads((killed / CFG_FILE).read_text()))


def test_nan_rows_stop_training_in_one_line_and_leave_no_sae_files(tmp_path):
    _, rows = planted_rows(400, seed=2)
    write_rows_run(tmp_path / "run", rows, episodes=2)
    shard = write_nan_row(tmp_path / "run")
    settings = PLANTED.model_copy(update={"training_rows": 2000, "checkpoints": 0})
    with pytest.raises(ValueError) as error:
        train_sae(RowSource(tmp_path / "run", LAYER), tmp_path / "sae", settings, layer=LAYER)
    assert str(error.value).startswith(f"{shard}: tensor `residuals` holds NaN or Inf") and "\n" not in str(error.value)
    left = sorted(p.name for p in (tmp_path / "sae").rglob("*")) if (tmp_path / "sae").exists() else []
    assert left == []


@pytest.mark.parametrize("architecture, saved_as", [("jumprelu", "jumprelu"), ("standard", "standard")])
def test_the_other_architectures_train_into_folders_both_loaders_read(tmp_path, architecture, saved_as):
    from sae_lens import SAE

    _, rows = planted_rows(512, seed=3)
    write_rows_run(tmp_path / "run", rows, episodes=2)
    settings = TrainSettings(architecture=architecture, d_sae=48, sparsity_coefficient=1e-3, batch_size=64,
                             training_rows=64 * 30, buffer_rows=512, checkpoints=1, device="cpu")
    calls = []
    out = train_sae(RowSource(tmp_path / "run", LAYER), tmp_path / "sae", settings, layer=LAYER,
                    progress=lambda done, total: calls.append((done, total)))
    assert calls == [(64 * step, 64 * 30) for step in range(31)]  # rows seen at the start and after each step
    theirs, ours = SAE.load_from_disk(out), load_sae(out)
    assert ours.cfg.architecture == saved_as == json.loads((out / CFG_FILE).read_text())["architecture"]
    with torch.no_grad():
        latents, norm = ours.encode_with_norm(rows[:100])
        assert torch.allclose(theirs.decode(theirs.encode(rows[:100])), ours.decode(latents, norm), atol=1e-5, rtol=0)


@pytest.mark.parametrize("changes, expected", [
    ({"k": 200, "d_sae": 128}, "k is 200, expected at most d_sae (128)"),
    ({"batch_size": 512, "training_rows": 100}, "batch_size is 512, expected at most training_rows (100)"),
])
def test_impossible_settings_are_refused_by_name(changes, expected):
    with pytest.raises(ValueError, match=re.escape(expected)):
        TrainSettings(**changes)
