"""Each step's cache key moves with every input that changes its output, and only with those.

Keys are computed the way Prefect does (`ContentKey.compute_key`) without a server: mutate one input,
compare keys. A stale key reuses old outputs; a needlessly moving one recomputes hours of capture.
"""

from __future__ import annotations

import json
import types
from pathlib import Path

import pytest
import torch
from safetensors.torch import load_file, save_file

from steering_core.capture import CaptureSettings
from steering_core.data.convert import EpisodeSource, SourcesRecord
from steering_core.pi05.spec import ModelSpec
from steering_core.storage.fileio import write_json
from steering_core.synthetic.pi05 import tiny_arch, write_pi05_checkpoint
from steering_core.synthetic.sae import write_sae_folder
from steering_core.synthetic.tokenizer import write_tokenizer
from steering_core.vectors.directions import SteeringSettings
from tasks.capture import capture_episodes
from tasks.sae import encode_concept

ARCH = tiny_arch()


def key_of(task, **parameters) -> str:
    """Return the cache key Prefect would compute for `task` called with `parameters`."""
    context = types.SimpleNamespace(task=types.SimpleNamespace(fn=task.fn))
    return task.cache_policy.compute_key(context, parameters, {})


def bump_tensor(path, name):
    """Add 1 to one element of one tensor of a safetensors file (a fine-tune of one weight)."""
    tensors = load_file(path)
    tensors[name].view(-1)[0] += 1
    save_file(tensors, path)


def sources_record(root, *, orientation="rotate180", sha=("a", "b")):
    episodes = [EpisodeSource(episode_index=i, file=f"f{i}.hdf5", demo="demo_0", sha256=s, task="open", length=3)
                for i, s in enumerate(sha)]
    record = SourcesRecord(repo_id="r", orientation=orientation, image_size=64, fps=10, robot_type="panda",
                           episodes=episodes)
    write_json(root / "meta" / "libero_sources.json", record.model_dump(mode="json"))


@pytest.fixture
def capture_call(tmp_path):
    checkpoint = write_pi05_checkpoint(tmp_path / "checkpoint", ARCH)
    tokenizer = write_tokenizer(tmp_path / "tokenizer.model")
    dataset = tmp_path / "dataset"
    sources_record(dataset)
    settings = CaptureSettings(model=ModelSpec(checkpoint=checkpoint, tokenizer=tokenizer, arch=ARCH), layers=(1,),
                               device="cpu", num_workers=0)
    return dict(label="group 0", dataset_root=str(dataset), repo_id="r", run_dir=str(tmp_path / "run"),
                settings=settings, episodes=[0])


def _model_file(call):
    return call["settings"].model.checkpoint / "model.safetensors"


CAPTURE_CHANGES = {
    "checkpoint tensor": (lambda c: bump_tensor(_model_file(c), next(iter(load_file(_model_file(c))))), True),
    "tokenizer": (lambda c: c["settings"].model.tokenizer.write_bytes(c["settings"].model.tokenizer.read_bytes() + b"x"),
                  True),
    "settings": (lambda c: c.update(settings=c["settings"].model_copy(update={"batch_size": 7, "layers": (2,)})),
                 True),
    "frames (orientation)": (lambda c: sources_record(_root(c), orientation="as_stored"), True),
    "the episode's demo": (lambda c: sources_record(_root(c), sha=("changed", "b")), True),
    "another episode's demo": (lambda c: sources_record(_root(c), sha=("a", "changed")), False),
    "frame readers": (lambda c: c.update(settings=c["settings"].model_copy(update={"num_workers": 3})), False),
    "label": (lambda c: c.update(label="another"), False),
}


def _root(call):
    return Path(call["dataset_root"])


@pytest.fixture
def encode_call(tmp_path):
    slice_path = tmp_path / "concept.safetensors"
    save_file({"residuals": torch.ones(4, 8)}, slice_path)
    sae = write_sae_folder(tmp_path / "sae", d_in=8, d_sae=16, hook_layer=1)
    settings = SteeringSettings(pairs_config=tmp_path / "pairs.json", output_root=tmp_path / "out", layer=1,
                                sae=str(sae), device="cpu", batch_size=4)
    return dict(pair="p", side="positive", layer=1, label="open", slice_path=str(slice_path), settings=settings)


ENCODE_CHANGES = {
    "residuals": (lambda c: bump_tensor(c["slice_path"], "residuals"), True),
    "SAE weights": (lambda c: bump_tensor(str(c["settings"].sae) + "/sae_weights.safetensors", "W_enc"), True),
    "SAE config": (lambda c: _edit_cfg(c), True),
    "top_k (report only)": (lambda c: c.update(settings=c["settings"].model_copy(update={"top_k": 3})), False),
}


def _edit_cfg(call):
    cfg_path = Path(call["settings"].sae) / "cfg.json"
    cfg = json.loads(cfg_path.read_text())
    cfg["apply_b_dec_to_input"] = not cfg["apply_b_dec_to_input"]
    cfg_path.write_text(json.dumps(cfg))


STEPS = {"capture": (capture_episodes, "capture_call", CAPTURE_CHANGES),
         "encode": (encode_concept, "encode_call", ENCODE_CHANGES)}


@pytest.mark.parametrize(("step", "change"), [(step, change) for step, (_, _, changes) in STEPS.items()
                                              for change in changes])
def test_key_moves_with_exactly_the_inputs_that_matter(request, step, change):
    task, fixture, changes = STEPS[step]
    call = request.getfixturevalue(fixture)
    before = key_of(task, **call)
    mutate, moves = changes[change]
    mutate(call)
    assert (key_of(task, **call) != before) is moves
