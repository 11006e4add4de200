"""Slicing a run whose shards stay in an S3 bucket (ranged reads) against slicing the same run from local disk.

The 10x run of bench.slicing_memory (40 one-episode shards, width 2048, float32), and the same rows in shards of
8 episodes (capture's `episodes_per_shard`), are written to local disk, copied under a mounted `s3://` root and
published file by file, as capture's tasks publish them, to a bucket of moto's S3 server on 127.0.0.1 (the
endpoint the tests use; a real bucket or MinIO is read the same way, through AWS_ENDPOINT_URL). Their shards are
then deleted from the mirror, so slicing reads them from the bucket with ranged GETs: each shard's header and row
columns, then only the runs of rows the concept map selects. Two selections of each run: the fixed pair of
bench.slicing_memory (frames 5-14 of the first 4 episodes, half of the rows of the shards holding them) and every
row of the run.

- Speed: seconds to slice from local disk (page cache warm) / seconds to slice from the bucket, same run, same
  map, same process, best of ROUNDS after a warm-up: at least 0.5x on loopback, in every case.
- Bytes: bytes fetched by ranged reads (`reads.Fetched`) / (the selected rows' bytes + each opened shard's
  header and row columns): at most 1.2x. The publication records read to check each shard's size and ETag on
  open are small JSON objects, not counted; `requests` counts every request the server saw (checks included).
- The endpoint's own cost: GETs of the opened shards whole, one request each, timed in the same rounds.

    uv run python -m bench.slicing_remote [--quick]
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import time
from pathlib import Path
from typing import Any

import torch

from bench.common import Result, cache_dir, command, finish, parser
from bench.slicing_memory import (
    BASE_EPISODES,
    FRAMES_PER_EPISODE,
    LAYER,
    SEGMENT_FRAMES,
    WIDTH,
    shard_files,
    write_map,
    write_run,
)

SCALE = 10  # the run: BASE_EPISODES x SCALE one-episode shards
GROUPED = 8  # the same rows again in shards of this many episodes (capture's episodes_per_shard)
ROUNDS = 5  # alternating local and bucket slicing, best kept
SPEED_TARGET = 0.5  # local seconds / bucket seconds, at least (issue 25, loopback)
BYTES_TARGET = 1.2  # fetched / (selected rows + headers), at most (issue 25)
BUCKET = "bench-slicing"
S3_ENV = {"AWS_ACCESS_KEY_ID": "bench", "AWS_SECRET_ACCESS_KEY": "bench", "AWS_DEFAULT_REGION": "us-east-1"}

QUICK = {"width": 64, "scale": 1}


class Requests(logging.Filter):
    """Counts the requests the S3 server logs (one line each), and drops the lines."""

    count = 0

    def filter(self, record: logging.LogRecord) -> bool:
        Requests.count += 1
        return False


def start_s3() -> Any:
    """Start moto's S3 server on a free loopback port and point the standard AWS variables at it; return it."""
    from moto.server import ThreadedMotoServer

    logging.getLogger("werkzeug").addFilter(Requests())
    server = ThreadedMotoServer(ip_address="127.0.0.1", port=0, verbose=False)
    server.start()
    host, port = server.get_host_and_port()
    os.environ.update(S3_ENV, AWS_ENDPOINT_URL=f"http://{host}:{port}")
    return server


def regroup(run_dir: Path, out: Path, episodes_per_shard: int) -> Path:
    """Write a run's rows again in shards of `episodes_per_shard` episodes (capture's setting), unless already there."""
    from safetensors.torch import load_file

    from steering_core.capture import shards

    if (out / shards.METADATA_FILE).is_file():
        return out
    shutil.rmtree(out, ignore_errors=True)
    metadata = shards.read_run_metadata(run_dir)
    spec = metadata.run.model_copy(update={"episodes_per_shard": episodes_per_shard})
    shards.write_run_spec(out, spec)
    by_episode = {record.episodes[0]: record for record in metadata.layer_shards(LAYER)}
    for key, members in shards.group_episodes(by_episode, episodes_per_shard).items():
        parts = [load_file(run_dir / by_episode[episode].file) for episode in members]
        rows = {name: torch.cat([part[name] for part in parts]) for name in (shards.RESIDUALS, *shards.ROW_COLUMNS)}
        shards.write_shard(out, spec, LAYER, key, shards.ShardRows(**rows), episodes=members, inputs="bench")
    shards.write_run_metadata(out)
    return out


def bucket_copy(run_dir: Path, mirror: Path) -> Path:
    """Publish a copy of the run under the mounted bucket root file by file, as capture's tasks publish their
    outputs, then delete its shards here; return its folder."""
    from steering_core.remote import publish

    copy = mirror / run_dir.name
    shutil.copytree(run_dir, copy)
    for file in sorted(copy.rglob("*")):
        if file.is_file():
            publish.publish(file)
    for shard in shard_files(copy):
        shard.unlink()
    return copy


def measure(local_run: Path, remote_run: Path, concept_map: Path, out: Path) -> dict[str, Any]:
    """Slice both runs ROUNDS times, alternating with GETs of the opened shards whole (the endpoint's own cost);
    return the best seconds of each, the bucket slicing's requests and bytes fetched, and the bytes selected."""
    from steering_core.capture.shards import RESIDUALS, read_run_metadata
    from steering_core.capture.slicing import SliceSettings, slice_concepts
    from steering_core.data.concept_map import read_concept_map
    from steering_core.layout import layer_dir
    from steering_core.remote import filesystems, reads
    from steering_core.storage import mirrors
    from steering_core.tensor_files import tensor_locations

    episodes = {row.episode_index for rows in read_concept_map(concept_map).concepts.values() for row in rows}
    opened = [r.file for r in read_run_metadata(local_run).layer_shards(LAYER) if episodes & set(r.episodes)]
    keys = [filesystems.object_path(mirrors.url_of(remote_run / file)) for file in opened]
    settings = SliceSettings(layers=(LAYER,))
    times: dict[str, list[float]] = {"local": [], "bucket": [], "whole GETs": []}
    for _round in range(ROUNDS + 1):  # round 0 warms up
        for side, run_dir in (("local", local_run), ("bucket", remote_run)):
            shutil.rmtree(out / side, ignore_errors=True)
            before, requests, start = reads.Fetched.total, Requests.count, time.perf_counter()
            slice_concepts(run_dir, concept_map, out / side, settings)
            times[side].append(time.perf_counter() - start)
        fetched, requests = reads.Fetched.total - before, Requests.count - requests
        start = time.perf_counter()
        whole = sum(len(fs.cat_file(key)) for fs, key in keys)
        times["whole GETs"].append(time.perf_counter() - start)
    slices = [{path.name: path.read_bytes() for path in (out / side / layer_dir(LAYER)).iterdir()}
              for side in ("local", "bucket")]
    indexes = [json.loads(files.pop("index.json")) | {"run_dir": ""} for files in slices]  # the runs' folders differ
    shutil.rmtree(out)
    locations = [tensor_locations(local_run / file)[RESIDUALS] for file in opened]
    selected = sum(entry["rows"] for entry in indexes[0]["concepts"].values()) * locations[0].row_bytes  # disjoint
    return {side: min(values[1:]) for side, values in times.items()} | {
        "fetched": fetched, "requests": requests, "whole": whole, "selected": selected, "shards": len(opened),
        "headers": sum(location.offset for location in locations),  # length, JSON header and row columns
        "same_slices": slices[0] == slices[1] and indexes[0] == indexes[1]}


def main(argv: list[str] | None = None) -> Result:
    """Run the benchmark; return the result."""
    args = parser(__doc__.splitlines()[0]).parse_args(argv)
    folder = cache_dir(args) / "slicing"
    width, scale = (QUICK["width"], QUICK["scale"]) if args.quick else (WIDTH, SCALE)
    episodes = BASE_EPISODES * scale
    local_run = write_run(folder / f"run-w{width}-x{scale}", episodes, width)
    maps = {
        "fixed pair": write_map(folder / f"map-fixed-x{scale}.json", list(range(BASE_EPISODES)), SEGMENT_FRAMES,
                                episodes * FRAMES_PER_EPISODE),
        "every row": write_map(folder / f"map-all-x{scale}.json", list(range(episodes)),
                               (0, FRAMES_PER_EPISODE - 1), episodes * FRAMES_PER_EPISODE),
    }
    runs = {"1-episode shards": local_run,
            f"{GROUPED}-episode shards": regroup(local_run, folder / f"run-w{width}-x{scale}-g{GROUPED}", GROUPED)}
    from steering_core.remote import filesystems
    from steering_core.storage import mirrors

    mirror_base = folder / "s3-mirror"
    shutil.rmtree(mirror_base, ignore_errors=True)
    os.environ[mirrors.MIRROR_ENV] = str(mirror_base)
    server = start_s3()
    try:
        filesystems.filesystem("s3").mkdir(BUCKET)
        mirror = mirrors.mount(f"s3://{BUCKET}")
        measured = {}
        for name, run_dir in runs.items():
            remote_run = bucket_copy(run_dir, mirror)
            for case, path in maps.items():
                measured[f"{name}, {case}"] = measure(run_dir, remote_run, path, folder / "remote-slices")
    finally:
        server.stop()
        shutil.rmtree(mirror_base, ignore_errors=True)
    rows = [_row(case, m) for case, m in measured.items()]
    speed = min(row["speed bucket / local"] for row in rows)
    bytes_ratio = max(row["fetched / (selected + headers)"] for row in rows)
    every = measured[f"{GROUPED}-episode shards, every row"]
    result = Result(
        name="slicing_remote",
        title="14. Slicing from an S3 bucket (ranged reads)",
        command=command("slicing_remote", args),
        measured=f"{every['selected'] / 2**20 / every['bucket']:,.0f} MiB/s from the bucket (every row); fetched "
                 f"{bytes_ratio:.3f}x of selected rows + headers",
        baseline=f"local disk {every['selected'] / 2**20 / every['local']:,.0f} MiB/s",
        ratio=speed,
        target=f">= {SPEED_TARGET}x of local disk (every case), fetched <= {BYTES_TARGET}x",
        met=speed >= SPEED_TARGET and bytes_ratio <= BYTES_TARGET and all(m["same_slices"] for m in measured.values()),
        table=rows,
        checks={"same_slices": all(m["same_slices"] for m in measured.values()), "bytes_ratio": bytes_ratio},
        notes=[
            f"run: {episodes} one-episode shards of {FRAMES_PER_EPISODE} frames x 10 tokens, width {width}, float32 "
            f"({sum(p.stat().st_size for p in shard_files(local_run)) / 2**20:.0f} MiB); moto's S3 server in this "
            f"process, on 127.0.0.1; best of {ROUNDS} after a warm-up, local page cache warm.",
            "the headline ratio is the smallest speed ratio of the four cases; the slices from the bucket equal "
            "the local ones byte for byte (checked; index.json apart from the run's folder).",
            f"where the time goes: a request costs about {_per_request_ms(measured):.1f} ms here ((bucket s - local "
            "s) / requests, every case pooled), so small shards pay for their 6 requests each (the record and a HEAD "
            "for the check, the length, the header, the row columns, the rows) more than for their bytes; GETting the "
            "opened shards whole, one request each, shows the endpoint's own bytes/s.",
            "how: every shard is opened through `tensor_files.open_read`; absent from the mirror, it is "
            "`reads.remote_file` (size and ETag checked against the publication record, then one ranged GET "
            "per read, no read-ahead). The first pass reads each opened shard's length, header and row columns "
            "(3 GETs); the second reads the runs of selected rows through the 8 MiB buffer, runs joined across "
            "their smallest gaps while the unselected rows read stay within 10% of the selected ones "
            "(steering_core/capture/slice_copy.py). Shards in a bucket are not CRC-checked whole (that would "
            "fetch every byte): their identity is the object's size and ETag.",
        ],
    )
    return finish(result, args)


def _per_request_ms(measured: dict[str, dict[str, Any]]) -> float:
    """Return the time the bucket's slicing takes beyond the local one, per request, in ms, over every case."""
    extra = sum(m["bucket"] - m["local"] for m in measured.values())
    return 1000 * extra / sum(m["requests"] for m in measured.values())


def _row(case: str, measured: dict[str, Any]) -> dict[str, Any]:
    """Return one table row from a measurement."""
    return {
        "selection": case,
        "shards opened": measured["shards"],
        "selected MiB": measured["selected"] / 2**20,
        "local s": measured["local"],
        "bucket s": measured["bucket"],
        "speed bucket / local": measured["local"] / measured["bucket"],
        "fetched MiB": measured["fetched"] / 2**20,
        "headers MiB": measured["headers"] / 2**20,
        "fetched / (selected + headers)": measured["fetched"] / (measured["selected"] + measured["headers"]),
        "requests": measured["requests"],
        "GET opened shards whole s": measured["whole GETs"],
        "whole GETs MiB/s": measured["whole"] / 2**20 / measured["whole GETs"],
    }


if __name__ == "__main__":
    main()
