"""Steps on a bucket root (moto's S3 server): tasks through `rooted`, and CLI commands given URLs.

Each "machine" is this process with all roots unmounted and a new, empty mirror folder: it shares nothing
with the previous one but the bucket and the Prefect server. Expectations come from the bytes the tests
write themselves (or a local run of the same command), never from the code under test.
"""

from __future__ import annotations

import hashlib
import json
import shutil
from dataclasses import dataclass
from pathlib import Path
from unittest.mock import ANY

import pytest
from prefect import flow, task
from typer.testing import CliRunner

from latent_steering_cli import app
from steering_core.config import RunConfig, load_run_config
from steering_core.demo import build_demo
from steering_core.remote import filesystems, publish, reads
from steering_core.storage import mirrors
from steering_core.storage.digests import file_digest
from tasks.cache_keys import content_key
from tasks.cache_records import CACHE_DIR, OUTPUTS
from tasks.results import RESULTS, rooted

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module", autouse=True)
def prefect_backend(prefect_server):
    """Every test here talks to the session's Prefect test server (tests/conftest.py)."""
    return prefect_server


def _fs():
    return filesystems.filesystem("s3")


def _objects(url: str) -> dict[str, bytes]:
    """Return key (relative to `url`) -> bytes of every object under `url`, read fresh from the bucket."""
    fs = _fs()
    fs.invalidate_cache()
    base = url[len("s3://"):]
    return {path[len(base) + 1:]: fs.cat_file(path) for path in fs.find(base)}


def _put(url: str, data: bytes) -> None:
    _fs().pipe_file(url[len("s3://"):], data)
    _fs().invalidate_cache()


def _machine(tmp_path: Path, monkeypatch, name: str, bucket: str) -> tuple[Path, Path]:
    """Start "another machine": no roots mounted, an empty mirror; return (data root, input root) mirrors."""
    mirrors.unmount_all()
    mirror = tmp_path / name
    assert not mirror.exists()
    monkeypatch.setenv(mirrors.MIRROR_ENV, str(mirror))
    return mirrors.mount(f"{bucket}/data"), mirrors.mount(f"{bucket}/inputs", role="input")


# ----------------------------------------------------------------------------- tasks through a bucket root

@task(cache_policy=content_key("steering_core.layout", source=file_digest), **RESULTS)
def double(source: str, output: str) -> dict:
    """Write the source's text twice into `output`."""
    Path(output).parent.mkdir(parents=True, exist_ok=True)
    Path(output).write_text(Path(source).read_text() * 2)
    return {OUTPUTS: [output]}


@task(cache_policy=content_key(source=file_digest), **RESULTS)
def shout(source: str, output: str) -> dict:
    """Write the source's text in capitals into `output`."""
    Path(output).parent.mkdir(parents=True, exist_ok=True)
    Path(output).write_text(Path(source).read_text().upper())
    return {OUTPUTS: [output]}


@flow
def first_step(root: str, source: str) -> tuple[str, dict]:
    state = rooted(double, root)(source, f"{root}/steps/doubled.txt", return_state=True)
    return state.name, state.result()


@flow
def two_steps(root: str, source: str) -> tuple[list[str], list]:
    first = rooted(double, root)(source, f"{root}/steps/doubled.txt", return_state=True)
    summary = first.result()
    second = rooted(shout, root)(summary[OUTPUTS][0], f"{root}/steps/shouted.txt", return_state=True)
    return [first.name, second.name], [summary, second.result(raise_on_failure=False)]


@flow
def next_step(root: str, source: str) -> tuple[str, object]:
    state = rooted(shout, root)(source, f"{root}/steps/shouted.txt", return_state=True)
    return state.name, state.result(raise_on_failure=False)


def _cache_records(bucket: str) -> dict[str, dict]:
    """Return cache record key -> the task summary it holds, read from the bucket with plain `json`."""
    return {key: json.loads(json.loads(data)["result"]) for key, data in _objects(f"{bucket}/data/{CACHE_DIR}").items()}


def test_a_task_publishes_its_output_and_keeps_its_record_in_the_bucket(bucket, tmp_path, monkeypatch):
    root, inputs = _machine(tmp_path, monkeypatch, "one", bucket)
    _put(f"{bucket}/inputs/words.txt", b"ab\n")
    name, summary = first_step(str(root), str(publish.pulled(inputs / "words.txt")))
    assert name == "Completed"
    assert summary == {OUTPUTS: [f"{bucket}/data/steps/doubled.txt"]}  # by URL, not by this machine's mirror
    stored = _objects(f"{bucket}/data")
    assert stored["steps/doubled.txt"] == b"ab\nab\n"
    record = json.loads(stored["steps/.doubled.txt.published.json"])
    assert record["files"]["doubled.txt"]["sha256"] == hashlib.sha256(b"ab\nab\n").hexdigest()
    assert record["files"]["doubled.txt"]["size"] == 6
    assert list(_cache_records(bucket).values()) == [summary]  # one record, in the bucket, holding the summary
    assert {key.split("/")[0] for key in stored} == {"steps", CACHE_DIR}
    assert publish.staging_files(bucket) == []


def test_another_machine_finds_the_task_cached_and_pulls_its_output(bucket, tmp_path, monkeypatch):
    root, inputs = _machine(tmp_path, monkeypatch, "one", bucket)
    _put(f"{bucket}/inputs/words.txt", b"ab\n")
    assert first_step(str(root), str(publish.pulled(inputs / "words.txt")))[0] == "Completed"

    root, inputs = _machine(tmp_path, monkeypatch, "two", bucket)
    names, (summary, shouted) = two_steps(str(root), str(inputs / "words.txt"))
    assert names == ["Cached", "Completed"]
    assert summary == {OUTPUTS: [f"{bucket}/data/steps/doubled.txt"]}
    assert (root / "steps" / "doubled.txt").read_bytes() == b"ab\nab\n"  # pulled into this machine's mirror
    assert shouted == {OUTPUTS: [f"{bucket}/data/steps/shouted.txt"]}
    assert _objects(f"{bucket}/data/steps")["shouted.txt"] == b"AB\nAB\n"
    assert len(_cache_records(bucket)) == 2


def test_an_input_changed_in_the_bucket_runs_the_task_again(bucket, tmp_path, monkeypatch):
    root, inputs = _machine(tmp_path, monkeypatch, "one", bucket)
    _put(f"{bucket}/inputs/words.txt", b"ab\n")
    source = str(inputs / "words.txt")
    assert two_steps(str(root), source)[0] == ["Completed", "Completed"]
    assert two_steps(str(root), source)[0] == ["Cached", "Cached"]
    _put(f"{bucket}/inputs/words.txt", b"cd\n")  # same size, new bytes
    assert two_steps(str(root), source)[0] == ["Completed", "Completed"]
    stored = _objects(f"{bucket}/data/steps")
    assert (stored["doubled.txt"], stored["shouted.txt"]) == (b"cd\ncd\n", b"CD\nCD\n")
    assert len(_cache_records(bucket)) == 4  # two keys per task

    root, inputs = _machine(tmp_path, monkeypatch, "two", bucket)  # the new content is what another machine sees
    assert two_steps(str(root), str(inputs / "words.txt"))[0] == ["Cached", "Cached"]
    assert (root / "steps" / "doubled.txt").read_bytes() == b"cd\ncd\n"


def test_an_output_altered_after_publication_fails_the_next_step_naming_it(bucket, tmp_path, monkeypatch):
    root, inputs = _machine(tmp_path, monkeypatch, "one", bucket)
    _put(f"{bucket}/inputs/words.txt", b"ab\n")
    assert first_step(str(root), str(inputs / "words.txt"))[0] == "Completed"
    url = f"{bucket}/data/steps/doubled.txt"
    altered = b"XY\nXY\n"  # same size, other bytes, no new record
    _put(url, altered)
    before = _objects(bucket)

    root, _ = _machine(tmp_path, monkeypatch, "two", bucket)
    name, error = next_step(str(root), url)
    assert name == "Failed"
    assert isinstance(error, ValueError)
    got, published = hashlib.sha256(altered).hexdigest(), hashlib.sha256(b"ab\nab\n").hexdigest()
    assert str(error).startswith(f"{url}: sha256 is {got}, expected {published}")
    assert "\n" not in str(error)
    after = _objects(bucket)
    new = {key: json.loads(json.loads(data)["result"]) for key, data in after.items() if key not in before}
    # no output, no cache record, no staging: only Prefect's record of the failure (its exception, by a random key)
    assert {key.split("/")[:2] == ["data", CACHE_DIR] for key in new} == {True} and len(new) == 1
    assert list(new.values())[0]["__exc_type__"] == "builtins.ValueError"
    assert {key: data for key, data in after.items() if key not in new} == before
    assert not (root / "steps" / "doubled.txt").exists() and not (root / "steps" / "shouted.txt").exists()


def test_a_record_whose_outputs_were_unpublished_runs_the_task_again(bucket, tmp_path, monkeypatch):
    root, inputs = _machine(tmp_path, monkeypatch, "one", bucket)
    _put(f"{bucket}/inputs/words.txt", b"ab\n")
    source = str(inputs / "words.txt")
    assert first_step(str(root), source)[0] == "Completed"
    _fs().rm_file(f"{bucket[5:]}/data/steps/.doubled.txt.published.json")
    _fs().invalidate_cache()
    assert first_step(str(root), source)[0] == "Completed"  # the local mirror copy does not count
    assert "steps/.doubled.txt.published.json" in _objects(f"{bucket}/data")
    assert first_step(str(root), source)[0] == "Cached"


def test_a_root_mounted_inside_a_published_folder_pulls_its_files(bucket, tmp_path, monkeypatch):
    root, _ = _machine(tmp_path, monkeypatch, "one", bucket)
    (root / "slices" / "layer01").mkdir(parents=True)
    (root / "slices" / "layer01" / "index.json").write_text('{"n": 1}')
    (root / "slices" / "top.json").write_text("{}")
    publish.publish(root / "slices")  # one record for the folder, beside it in data/

    _machine(tmp_path, monkeypatch, "two", bucket)
    mirrors.unmount_all()
    inner = mirrors.mount(f"{bucket}/data/slices")  # e.g. a command given the folder's URL
    assert sorted(publish.pull(inner / "layer01")) == [inner / "layer01" / "index.json"]
    assert sorted(publish.pull(inner)) == [inner / "top.json"]
    assert (inner / "layer01" / "index.json").read_text() == '{"n": 1}' and (inner / "top.json").read_text() == "{}"



def test_a_folder_republished_from_a_mirror_without_its_shards_keeps_them(bucket, tmp_path, monkeypatch):
    root, _ = _machine(tmp_path, monkeypatch, "one", bucket)
    (root / "run" / "layer01").mkdir(parents=True)
    shard = bytes(range(256)) * 16
    (root / "run" / "layer01" / "shard-00000.safetensors").write_bytes(shard)
    (root / "run" / "run.json").write_text('{"v": 1}')
    publish.publish(root / "run")

    root, _ = _machine(tmp_path, monkeypatch, "two", bucket)
    publish.pull(root / "run")
    assert not (root / "run" / "layer01" / "shard-00000.safetensors").exists()  # streamed, never pulled
    (root / "run" / "run.json").write_text('{"v": 2}')  # e.g. a capture resumed here rewrites its run.json
    publish.publish(root / "run")
    assert _objects(f"{bucket}/data/run") == {"layer01/shard-00000.safetensors": shard, "run.json": b'{"v": 2}'}
    assert sorted(_published(f"{bucket}/data/run")["files"]) == ["run/layer01/shard-00000.safetensors", "run/run.json"]
    assert reads.remote_file(root / "run" / "layer01" / "shard-00000.safetensors").size == len(shard)


# ----------------------------------------------------------------------------- CLI commands given URLs

@dataclass(frozen=True)
class Local:
    """The demo's inputs and the steps run with local paths only: what the URL runs must equal."""

    config: RunConfig
    out: Path  # arch.json, libero_lerobot/<repo>/, manifest.json, concept_map.json, run/, slices/

    @property
    def dataset(self) -> Path:
        return self.out / "libero_lerobot" / self.config.dataset.repo_id

    def manifest_args(self, output: str | Path) -> list[str]:
        pair = self.config.pairs[0]
        return ["manifest", "--lerobot-root", str(self.dataset), "--task-a-text", pair.positive, "--task-b-text",
                pair.negative, "--output", str(output), "--repo-id", self.config.dataset.repo_id]

    def concept_map_args(self, manifest: str | Path, output: str | Path, dataset: str | Path | None = None) -> list[str]:
        return ["concept-map", "--manifest-path", str(manifest), "--output-path", str(output), "--lerobot-root",
                str(dataset or self.dataset), "--repo-id", self.config.dataset.repo_id]

    def capture_args(self, output: str | Path) -> list[str]:
        model = self.config.model
        return ["capture", "--checkpoint-path", str(model.checkpoint), "--tokenizer-path", str(model.tokenizer),
                "--lerobot-root", str(self.dataset), "--repo-id", self.config.dataset.repo_id, "--output-dir",
                str(output), "--layers", "1", "--batch-size", str(self.config.capture.batch_size), "--device", "cpu",
                "--num-workers", "0", "--arch-file", str(self.out / "arch.json")]

    def slice_args(self, run_dir: str | Path, concept_map: str | Path, output: str | Path) -> list[str]:
        return ["slice", "--run-dir", str(run_dir), "--concept-map-path", str(concept_map), "--output-dir",
                str(output), "--layers", "1"]


def cli(*args: str | Path) -> str:
    result = CliRunner().invoke(app, [str(arg) for arg in args])
    assert result.exit_code == 0, (args[0], result.output, result.exception)
    return result.output


@pytest.fixture(scope="module")
def local(tmp_path_factory) -> Local:
    """The demo inputs (2 demos per task), converted, and one pair's manifest, concept map, layer-1 capture and
    slices written with local paths (about 20 s)."""
    base = tmp_path_factory.mktemp("bucket_cli")
    config = load_run_config(build_demo(base / "demo", demos_per_task=2))
    world = Local(config, base / "out")
    world.out.mkdir()
    (world.out / "arch.json").write_text(config.model.arch.model_dump_json())
    pair = config.pairs[0]
    cli("filter", "--input-dir", config.sources.folders[0], "--output-dir", world.out / "filtered",
        "--task", pair.positive, "--task", pair.negative)
    cli("convert", "--input-dir", world.out / "filtered", "--repo-id", config.dataset.repo_id, "--output-dir",
        world.dataset, "--image-size", str(config.dataset.image_size))
    cli(*world.manifest_args(world.out / "manifest.json"))
    cli(*world.concept_map_args(world.out / "manifest.json", world.out / "concept_map.json"))
    cli(*world.capture_args(world.out / "run"))
    cli(*world.slice_args(world.out / "run", world.out / "concept_map.json", world.out / "slices"))
    return world


def _published(url: str) -> dict:
    """Return the publication record of the output `url`, read from the bucket with plain `json`."""
    parent, name = url.rsplit("/", 1)
    return json.loads(_objects(parent)[f".{name}.published.json"])


def test_manifest_and_concept_map_write_to_and_read_from_bucket_urls(local, bucket, tmp_path, monkeypatch):
    _machine(tmp_path, monkeypatch, "one", bucket)
    manifest, concept_map = f"{bucket}/data/manifests/pair.json", f"{bucket}/data/manifests/pair_concept_map.json"
    cli(*local.manifest_args(manifest))
    expected = (local.out / "manifest.json").read_bytes()
    assert _objects(f"{bucket}/data/manifests")["pair.json"] == expected
    assert _published(manifest)["files"] == {"pair.json": {
        "size": len(expected), "sha256": hashlib.sha256(expected).hexdigest(), "etag": ANY}}

    _machine(tmp_path, monkeypatch, "two", bucket)
    cli(*local.concept_map_args(manifest, concept_map))
    # the concept map names its manifest: by URL here, by the local path there; nothing else differs
    local_map = (local.out / "concept_map.json").read_bytes()
    expected = local_map.replace(str(local.out / "manifest.json").encode(), manifest.encode())
    assert expected != local_map
    assert _objects(f"{bucket}/data/manifests")["pair_concept_map.json"] == expected
    assert _published(concept_map)["files"]["pair_concept_map.json"]["sha256"] == hashlib.sha256(expected).hexdigest()
    assert publish.staging_files(bucket) == []


def _files(folder: Path) -> dict[str, bytes]:
    """Return relative path -> bytes of every file under a local folder (lock files left out)."""
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in sorted(folder.rglob("*"))
            if p.is_file() and not p.name.endswith(".lock")}


def test_a_dataset_uploaded_by_hand_is_read_from_its_url(local, bucket, tmp_path, monkeypatch):
    dataset = f"{bucket}/datasets/{local.config.dataset.repo_id}"
    for relative, data in _files(local.dataset).items():
        _put(f"{dataset}/{relative}", data)
    _machine(tmp_path, monkeypatch, "one", bucket)
    args = local.manifest_args(f"{bucket}/data/manifest.json")
    args[args.index("--lerobot-root") + 1] = dataset
    cli(*args)
    expected = (local.out / "manifest.json").read_bytes().replace(str(local.dataset).encode(), dataset.encode())
    assert expected != (local.out / "manifest.json").read_bytes()  # it names its dataset
    assert _objects(f"{bucket}/data")["manifest.json"] == expected
    assert _objects(dataset) == _files(local.dataset)  # an input: read, never republished (no record beside it)


def test_capture_to_a_bucket_and_slice_it_on_another_machine(local, bucket, tmp_path, monkeypatch):
    run, slices = f"{bucket}/data/residuals/demo", f"{bucket}/data/slices"
    _machine(tmp_path, monkeypatch, "one", bucket)
    cli(*local.capture_args(run))
    captured = _objects(run)
    assert captured == _files(local.out / "run")  # every shard and JSON file as the local capture wrote it
    assert sorted(_published(run)["files"]) == sorted(f"demo/{name}" for name in captured)

    mirror, _ = _machine(tmp_path, monkeypatch, "two", bucket)
    cli(*local.slice_args(run, local.out / "concept_map.json", slices))
    assert _objects(run) == captured and sorted(_published(run)["files"]) == sorted(f"demo/{n}" for n in captured)
    assert not list(mirror.rglob("shard-*.safetensors"))  # shards were read from the bucket, not pulled
    expected = {name: data.replace(str(local.out / "run").encode(), run.encode())
                for name, data in _files(local.out / "slices").items()}
    assert expected["layer01/index.json"] != _files(local.out / "slices")["layer01/index.json"]  # names its run
    assert _objects(slices) == expected
    assert publish.staging_files(bucket) == []


def test_a_finished_capture_run_again_on_another_machine_captures_nothing(local, bucket, tmp_path, monkeypatch):
    run = f"{bucket}/data/residuals/demo"
    _machine(tmp_path, monkeypatch, "one", bucket)
    cli(*local.capture_args(run))
    captured = _objects(f"{bucket}/data")
    _machine(tmp_path, monkeypatch, "two", bucket)
    output = cli(*local.capture_args(run))
    assert _objects(f"{bucket}/data") == captured
    assert ": 0 shard group(s) written" in output, output


def test_a_file_uploaded_by_hand_is_read_from_its_url(local, bucket, tmp_path, monkeypatch):
    manifest = f"{bucket}/hand/manifest.json"
    _put(manifest, (local.out / "manifest.json").read_bytes())
    _machine(tmp_path, monkeypatch, "one", bucket)
    cli(*local.concept_map_args(manifest, tmp_path / "concept_map.json"))
    local_map = (local.out / "concept_map.json").read_bytes()
    expected = local_map.replace(str(local.out / "manifest.json").encode(), manifest.encode())
    assert expected != local_map and (tmp_path / "concept_map.json").read_bytes() == expected
    assert _objects(f"{bucket}/hand") == {"manifest.json": (local.out / "manifest.json").read_bytes()}


def test_an_altered_file_of_a_published_folder_fails_the_command_naming_it(local, bucket, tmp_path, monkeypatch):
    root, _ = _machine(tmp_path, monkeypatch, "one", bucket)
    manifests = root / "manifests"  # a folder published whole, as a step publishes its output folder
    manifests.mkdir(parents=True)
    (manifests / "pair.json").write_bytes((local.out / "manifest.json").read_bytes())
    publish.publish(manifests)
    url = f"{bucket}/data/manifests/pair.json"
    altered = (local.out / "manifest.json").read_bytes().replace(b'"effect_size": ', b'"effect_size":-')
    assert len(altered) == (local.out / "manifest.json").stat().st_size
    _put(url, altered)
    before = _objects(bucket)

    _machine(tmp_path, monkeypatch, "two", bucket)
    result = CliRunner().invoke(app, local.concept_map_args(url, f"{bucket}/data/manifests/pair_concept_map.json"))
    assert result.exit_code == 1, (result.output, result.exception)
    assert result.output.strip().splitlines() == [
        f"error: --manifest-path: {url}: sha256 is {hashlib.sha256(altered).hexdigest()}, expected "
        f"{hashlib.sha256((local.out / 'manifest.json').read_bytes()).hexdigest()} from its publication record; "
        f"the object changed after it was published; {publish.REDO_HINT}"]
    assert _objects(bucket) == before


def test_a_capture_resumed_on_a_machine_with_its_dataset_elsewhere_keeps_its_shards(local, bucket, tmp_path,
                                                                                    monkeypatch):
    run = f"{bucket}/data/residuals/demo"
    _machine(tmp_path, monkeypatch, "one", bucket)
    cli(*local.capture_args(run))
    shards = {name: data for name, data in _objects(run).items() if name.endswith(".safetensors")}
    assert shards and shards == {n: d for n, d in _files(local.out / "run").items() if n.endswith(".safetensors")}

    _machine(tmp_path, monkeypatch, "two", bucket)
    copy = tmp_path / "datasets" / local.config.dataset.repo_id  # the same dataset at another path on this machine
    shutil.copytree(local.dataset, copy)
    args = local.capture_args(run)
    args[args.index("--lerobot-root") + 1] = str(copy)
    cli(*args)
    after = _objects(run)
    assert {name: data for name, data in after.items() if name.endswith(".safetensors")} == shards
    assert sorted(_published(run)["files"]) == sorted(f"demo/{name}" for name in after)
    assert str(copy) in json.loads(after["run.json"])["sources"]["dataset_root"]  # the run names where it was read
