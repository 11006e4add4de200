"""The whole pipeline on an existing LeRobot dataset read in place (`dataset.existing`), in Prefect's test harness.

The same demos go through the hdf5 path (filter, convert to v3.0, ...) and, converted once to v2.1
by our writer and made read-only like a shared Hugging Face cache, through `latent-steering run`
with `dataset.existing`; then through a v2.0 copy spread over three chunks without
`episodes_stats.jsonl` or our `libero_sources.json`, as openpi's physical-intelligence/libero is.
Manifests, concept maps, slices and steering vectors must be equal; the dataset folders must be
untouched; a refresh on the unchanged dataset must run nothing.
"""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import pytest
import torch
from helpers_libero import tiny_task
from prefect.client.orchestration import get_client
from safetensors.torch import load_file
from test_flows import flow_runs_under, invoke
from test_lerobot_v2 import CLOSE, DEMOS, OPEN, make_read_only, make_writable, tree_listing

from flows.pipeline import latent_steering
from flows.refresh import refresh
from steering_core.config import (
    CaptureSection,
    DatasetSection,
    EvaluateSection,
    ModelSection,
    PairSection,
    RunConfig,
    SaeSection,
    SourcesSection,
    SteeringSection,
    load_run_config,
    write_run_config,
)
from steering_core.data.convert import SOURCES_FILE, ConvertSettings, convert_libero
from steering_core.data.dataset import read_meta
from steering_core.layout import layer_dir
from steering_core.preflight import PreflightError
from steering_core.storage.fileio import read_json
from steering_core.synthetic.libero import write_libero_file
from steering_core.synthetic.pi05 import tiny_arch, write_pi05_checkpoint
from steering_core.synthetic.sae import write_sae_folder
from steering_core.synthetic.tokenizer import write_tokenizer

pytestmark = pytest.mark.slow
os.environ.setdefault("HF_HUB_OFFLINE", "1")

ARCH = tiny_arch()
LAYER = 1
PAIR = "open_vs_close"


@pytest.fixture(scope="module", autouse=True)
def prefect_backend(prefect_server):
    """Every test here talks to the session's Prefect test server (tests/conftest.py)."""
    return prefect_server


@pytest.fixture(scope="module")
def inputs(tmp_path_factory) -> dict[str, Path]:
    """Demo files, a tiny model, tokenizer and SAE; the demos as a read-only v2.1 and a read-only v2.0 in 3 chunks."""
    root = tmp_path_factory.mktemp("existing")
    demos = root / "demos"
    demos.mkdir()
    write_libero_file(demos, tiny_task(OPEN, axis=2, direction=1), num_demos=3, settings=DEMOS)
    write_libero_file(demos, tiny_task(CLOSE, axis=2, direction=-1), num_demos=3, settings=DEMOS)
    v21, v20 = root / "hub" / "libero", root / "hub_v20" / "libero"
    convert_libero([demos], v21, ConvertSettings(repo_id="local/libero", image_size=DEMOS.image_size,
                                                 codebase_version="v2.1"))
    shutil.copytree(v21, v20)
    # openpi's dataset: v2.0, no per-episode stats, not converted by us, episodes over several chunks
    (v20 / "meta/episodes_stats.jsonl").unlink()
    (v20 / SOURCES_FILE).unlink()
    info = json.loads((v20 / "meta/info.json").read_text())
    (v20 / "meta/info.json").write_text(json.dumps({**info, "codebase_version": "v2.0", "chunks_size": 2,
                                                    "total_chunks": 3}, indent=4))
    for episode in range(info["total_episodes"]):
        target = v20 / f"data/chunk-{episode // 2:03d}/episode_{episode:06d}.parquet"
        target.parent.mkdir(exist_ok=True)
        (v20 / f"data/chunk-000/episode_{episode:06d}.parquet").rename(target)
    make_read_only(v21)
    make_read_only(v20)
    paths = {
        "demos": demos, "v21": v21, "v20": v20,
        "checkpoint": write_pi05_checkpoint(root / "checkpoint", ARCH),
        "tokenizer": write_tokenizer(root / "tokenizer.model"),
        "sae": write_sae_folder(root / "sae", d_in=ARCH.width, d_sae=32, hook_layer=LAYER),
    }
    yield paths
    make_writable(v21)
    make_writable(v20)


def write_config(folder: Path, inputs: dict[str, Path], *, sources: SourcesSection | None,
                 dataset: DatasetSection) -> Path:
    """Write the run config of one pair at one layer (tiny sizes) under `folder`; return its path."""
    config = RunConfig(
        name="existing",
        output_root=folder / "data",
        sources=sources,
        dataset=dataset,
        pairs=(PairSection(name=PAIR, positive=OPEN, negative=CLOSE),),
        layers=(LAYER,),
        model=ModelSection(checkpoint=inputs["checkpoint"], tokenizer=inputs["tokenizer"], arch=ARCH),
        capture=CaptureSection(batch_size=4, device="cpu", num_workers=0),
        sae={LAYER: SaeSection(path=inputs["sae"])},
        steering=SteeringSection(device="cpu", batch_size=16, top_k=5),
        # phase 4 reads frames from the dataset in place too; the smallest evaluation (the default one was 60% of
        # the time here): its measurements are under test elsewhere
        evaluate=EvaluateSection(max_frames=2, noise_seeds=1, alphas=(-1.0, 0.0, 1.0), random_directions=8,
                                 permutations=0, bootstrap=20, device="cpu"),
    )
    return write_run_config(config, folder / "run.yaml")


@pytest.fixture(scope="module")
def hdf5_run(inputs, tmp_path_factory) -> Path:
    """The usual path: filter and convert the demo files (v3.0), then everything else."""
    path = write_config(tmp_path_factory.mktemp("hdf5"), inputs, sources=SourcesSection(folders=(inputs["demos"],)),
                        dataset=DatasetSection(repo_id="local/libero", image_size=DEMOS.image_size))
    latent_steering(str(path))
    return path


def run_existing(inputs: dict[str, Path], key: str, folder: Path) -> tuple[Path, dict[str, int], str]:
    """`latent-steering run --config` on the read-only dataset `inputs[key]`; return config, tree before, output."""
    path = write_config(folder, inputs, sources=None, dataset=DatasetSection(existing=inputs[key]))
    before = tree_listing(inputs[key])
    result = invoke("run", "--config", str(path))
    return path, before, result.output


@pytest.fixture(scope="module")
def v21_run(inputs, tmp_path_factory):
    return run_existing(inputs, "v21", tmp_path_factory.mktemp("v21"))


@pytest.fixture(scope="module")
def v20_run(inputs, tmp_path_factory):
    return run_existing(inputs, "v20", tmp_path_factory.mktemp("v20"))


def without_file(rows: list[dict]) -> list[dict]:
    """Return manifest segments without `file` (hdf5 path: the converted dataset's; here: the episode parquet)."""
    return [{k: v for k, v in row.items() if k != "file"} for row in rows]


def assert_same_outputs(ours: Path, theirs: Path, dataset: Path) -> None:
    """Manifests (but `file`), concept maps, slices and steering vectors of two runs are equal."""
    a, b = load_run_config(ours), load_run_config(theirs)
    pair_a, pair_b = a.pair(PAIR), b.pair(PAIR)
    manifest_a, manifest_b = read_json(a.manifest_path(pair_a)), read_json(b.manifest_path(pair_b))
    assert manifest_a["axis"] == manifest_b["axis"]
    assert without_file(manifest_a["segments"]) == without_file(manifest_b["segments"])
    for segment in manifest_a["segments"]:  # the seed's `file`: the per-episode parquet, relative to the dataset
        assert (dataset / segment["file"]).is_file() and segment["file"].endswith(f"{segment['demo']}.parquet")
    concepts_a = read_json(a.concept_map_path(pair_a))["concepts"]
    assert concepts_a == read_json(b.concept_map_path(pair_b))["concepts"] and set(concepts_a) == {OPEN, CLOSE}
    for concept in (OPEN, CLOSE):
        name = f"{concept}.pt"
        slice_a = torch.load(a.slices_dir(pair_a) / layer_dir(LAYER) / name, weights_only=True)
        slice_b = torch.load(b.slices_dir(pair_b) / layer_dir(LAYER) / name, weights_only=True)
        assert torch.equal(slice_a, slice_b) and slice_a.numel() > 0
    vectors = sorted((a.layer_path(LAYER) / PAIR).glob("*.safetensors"))
    assert {p.stem for p in vectors} >= {"latent_direction", "residual_direction"}
    for path in vectors:
        ta, tb = load_file(path), load_file(b.layer_path(LAYER) / PAIR / path.name)
        assert ta.keys() == tb.keys() and all(torch.equal(ta[k], tb[k]) for k in ta), path.name
        assert any(t.abs().sum() > 0 for t in ta.values())


def assert_read_in_place(config_path: Path, dataset: Path, before: dict[str, int]) -> None:
    """Nothing was written into, converted from or copied out of the dataset folder."""
    config = load_run_config(config_path)
    assert config.dataset_root == dataset and tree_listing(dataset) == before
    produced = {p.name for p in config.output_root.iterdir()}
    assert "libero_lerobot" not in produced and "libero_filtered" not in produced, produced


def test_v21_in_place_equals_the_hdf5_path(hdf5_run, v21_run, inputs):
    path, before, output = v21_run
    assert f"report: {load_run_config(path).layer_path(LAYER) / 'summary.md'}" in output
    assert_read_in_place(path, inputs["v21"], before)
    assert_same_outputs(path, hdf5_run, inputs["v21"])


def test_v20_in_several_chunks_equals_the_hdf5_path(hdf5_run, v20_run, inputs):
    path, before, _ = v20_run
    assert [e.data_file for e in read_meta(inputs["v20"]).episodes][-1] == "data/chunk-002/episode_000005.parquet"
    assert_read_in_place(path, inputs["v20"], before)
    assert_same_outputs(path, hdf5_run, inputs["v20"])


def test_refresh_on_an_unchanged_dataset_runs_nothing(v21_run, inputs):
    path, before, _ = v21_run
    state = refresh(str(path), return_state=True)
    assert state.result() == {"ran": False, "changes": f"dataset {inputs['v21'].resolve()}: content unchanged"}
    with get_client(sync_client=True) as client:
        assert len(flow_runs_under(client, state.state_details.flow_run_id)) == 1  # no pipeline subflow
    assert tree_listing(inputs["v21"]) == before


def test_a_missing_dataset_is_named_before_anything_runs(inputs, tmp_path):
    path = write_config(tmp_path, inputs, sources=None, dataset=DatasetSection(existing=tmp_path / "nowhere"))
    with pytest.raises(PreflightError, match=r"nowhere: LeRobot dataset folder not found"):
        latent_steering(str(path))
    assert not (tmp_path / "data" / "manifests").exists()
