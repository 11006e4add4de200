"""Slicing throughput against its I/O floor, and peak resident memory while slicing runs 1x, 10x and 100x as large.

Runs are written directly with `steering_core.capture.shards` (one shard per episode, real width 2048, float32),
as capture would write them. Two questions:

- Memory: a concept pair's segments stay the same while the run around them grows, as when one pair is
  sliced out of a capture of a whole suite. `slice_concepts` streams shard by shard, so its peak resident
  memory (VmHWM of a fresh process per size) must stay flat: within 1.5x from 1x to 100x.
- Throughput: concepts covering every captured row of the 10x run, so slicing reads every residual and
  writes it back out (.pt and .safetensors); MiB/s of shard bytes against the I/O floor of that work,
  reading the same files and writing their bytes twice, in the same process (page cache warm for both):
  at least 0.5x. A plain sequential read is reported too.

    uv run python -m bench.slicing_memory [--device cuda] [--quick]
"""

from __future__ import annotations

import argparse
import shutil
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

from bench.common import (
    Result,
    cache_dir,
    command,
    finish,
    parser,
    peak_rss_mib,
    print_child_result,
    rss_mib,
    run_child,
)
from steering_core.devices import resolve_device

# ----------------------------------------------------------------------------- settings

WIDTH = 2048  # Gemma-2B residual width
LAYER = 12
FRAMES_PER_EPISODE = 20
TOKENS_PER_FRAME = 10  # instruction tokens kept per frame
BASE_EPISODES = 4  # the 1x run: 800 rows, 6.25 MiB of residuals
SCALES = (1, 10, 100)  # 100x: 400 episodes, 625 MiB
THROUGHPUT_SCALE = 10  # every row of this run (one of SCALES) is sliced for the MiB/s comparison
SEGMENT_FRAMES = (5, 14)  # the fixed pair's window in each of the base episodes (inclusive)
READ_CHUNK = 8 << 20  # bytes per read() of the plain sequential read
ROUNDS = 5  # throughput: alternating rounds of slicing, plain read and read-write floor, best kept
TARGET = 1.5  # largest peak RSS / smallest, at most
THROUGHPUT_TARGET = 0.5  # slicing MiB/s / (read the shards + write their bytes twice) MiB/s, at least (issue 16)

QUICK = {"width": 64, "scales": (1, 10), "throughput_scale": 1}

TOKEN_OFFSET = 2 * 256 + 1  # prefix position of the first instruction token (after two cameras and BOS)
CONCEPTS = ("open the top drawer of the cabinet", "close the top drawer of the cabinet")


# ----------------------------------------------------------------------------- inputs


def write_run(run_dir: Path, episodes: int, width: int) -> Path:
    """Write a run of `episodes` one-episode shards through `steering_core.capture.shards`, unless already there."""
    from steering_core.capture.shards import (
        METADATA_FILE,
        RunSpec,
        ShardRows,
        shard_key,
        write_run_metadata,
        write_run_spec,
        write_shard,
    )

    if (run_dir / METADATA_FILE).is_file():
        return run_dir
    shutil.rmtree(run_dir, ignore_errors=True)
    spec = RunSpec(
        token_type="instructions", layers=(LAYER,), width=width, inputs={"generator": "bench.slicing_memory"}
    )
    write_run_spec(run_dir, spec)
    generator = torch.Generator().manual_seed(0)
    rows = FRAMES_PER_EPISODE * TOKENS_PER_FRAME
    frame = np.repeat(np.arange(FRAMES_PER_EPISODE), TOKENS_PER_FRAME)
    position = np.tile(np.arange(TOKENS_PER_FRAME), FRAMES_PER_EPISODE) + TOKEN_OFFSET
    for episode in range(episodes):
        shard = ShardRows(
            residuals=torch.randn(rows, width, generator=generator),
            index=torch.from_numpy(episode * FRAMES_PER_EPISODE + frame),
            episode_index=torch.full((rows,), episode, dtype=torch.int64),
            frame_index=torch.from_numpy(frame),
            token_position=torch.from_numpy(position),
            token_id=torch.from_numpy(position % 97 + 3),
        )
        write_shard(run_dir, spec, LAYER, shard_key(episode), shard, episodes=(episode,), inputs="bench")
    write_run_metadata(run_dir)
    return run_dir


def write_map(path: Path, episodes: list[int], frames: tuple[int, int], total_frames: int) -> Path:
    """Write a concept map whose two concepts take alternate episodes, frames `frames` of each."""
    from steering_core.data.concept_map import ConceptMap, ConceptRow, write_concept_map

    concepts: dict[str, list[ConceptRow]] = {concept: [] for concept in CONCEPTS}
    first, last = frames
    for number, episode in enumerate(episodes):
        start = episode * FRAMES_PER_EPISODE + first
        concepts[CONCEPTS[episode % 2]].append(ConceptRow(
            segment_id=number, episode_index=episode, frame_start=first, frame_end=last,
            observed_frame_start=first, observed_frame_end=last,
            start_index=start, end_index=start + last - first, length=last - first + 1,
        ))
    concept_map = ConceptMap(
        manifest="generated by bench.slicing_memory", lerobot_root="none", repo_id="bench/slicing",
        concept_count={concept: len(rows) for concept, rows in concepts.items()}, sample_count=total_frames,
        concepts={concept: tuple(rows) for concept, rows in concepts.items()},
    )
    return write_concept_map(concept_map, path)


def shard_files(run_dir: Path) -> list[Path]:
    """Return the run's shard files in episode order."""
    return sorted(run_dir.rglob("shard-*.safetensors"))


# ----------------------------------------------------------------------------- child measurements


def plain_read(files: list[Path]) -> float:
    """Read every file front to back in READ_CHUNK pieces; return the seconds taken."""
    start = time.perf_counter()
    for path in files:
        with open(path, "rb", buffering=0) as handle:
            while handle.read(READ_CHUNK):
                pass
    return time.perf_counter() - start


def read_write_twice(files: list[Path], out: Path) -> float:
    """Read every file and write its bytes to two output files, slicing's I/O floor; return the seconds taken."""
    out.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    with open(out / "copy-a", "wb") as first, open(out / "copy-b", "wb") as second:
        for path in files:
            with open(path, "rb", buffering=0) as handle:
                while chunk := handle.read(READ_CHUNK):
                    first.write(chunk)
                    second.write(chunk)
    seconds = time.perf_counter() - start
    shutil.rmtree(out)
    return seconds


def child_memory(run_dir: Path, concept_map: Path, out: Path, device: str) -> dict[str, Any]:
    """Slice once in this fresh process; return its peak RSS, the RSS before slicing, and the time."""
    from steering_core.capture.slicing import SliceSettings, slice_concepts

    before = rss_mib()
    start = time.perf_counter()
    slice_concepts(run_dir, concept_map, out, SliceSettings(layers=(LAYER,), device=device))
    seconds = time.perf_counter() - start
    peak = peak_rss_mib()
    shutil.rmtree(out, ignore_errors=True)
    return {"peak_rss_mib": peak, "rss_before_mib": before, "seconds": seconds, "shard_bytes": _bytes(run_dir)}


def child_throughput(run_dir: Path, concept_map: Path, out: Path, device: str) -> dict[str, Any]:
    """Time slicing, a plain read and a read-and-write-twice of the same shards.

    The three alternate for ROUNDS rounds after a warm-up; the best of each is returned.
    """
    from steering_core.capture.slicing import SliceSettings, slice_concepts

    files = shard_files(run_dir)
    settings = SliceSettings(layers=(LAYER,), device=device)
    slice_concepts(run_dir, concept_map, out, settings)  # warm-up; also warms the page cache
    times: dict[str, list[float]] = {"seconds": [], "read_seconds": [], "floor_seconds": []}
    for _ in range(ROUNDS):
        shutil.rmtree(out)  # both sides write into a fresh place: removing old outputs is timed on neither
        start = time.perf_counter()
        slice_concepts(run_dir, concept_map, out, settings)
        times["seconds"].append(time.perf_counter() - start)
        times["read_seconds"].append(plain_read(files))
        times["floor_seconds"].append(read_write_twice(files, out / "floor"))
    shutil.rmtree(out, ignore_errors=True)
    return {name: min(values) for name, values in times.items()} | {"shard_bytes": _bytes(run_dir)}


def _bytes(run_dir: Path) -> int:
    """Return the total size of the run's shard files."""
    return sum(path.stat().st_size for path in shard_files(run_dir))


# ----------------------------------------------------------------------------- benchmark


def main(argv: list[str] | None = None) -> Result | None:
    """Run the benchmark (or, with --child, one measurement in this process); return the result."""
    arguments = parser(__doc__.splitlines()[0])
    arguments.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    arguments.add_argument("--run-dir", type=Path, help=argparse.SUPPRESS)
    arguments.add_argument("--concept-map", type=Path, help=argparse.SUPPRESS)
    arguments.add_argument("--throughput-map", type=Path, help=argparse.SUPPRESS)
    args = arguments.parse_args(argv)
    device = resolve_device(args.device)
    folder = cache_dir(args) / "slicing"
    if args.child:  # memory first (the process's peak so far), then throughput, which may raise the peak
        out = folder / "slices"
        measured = child_memory(args.run_dir, args.concept_map, out, str(device))
        if args.throughput_map is not None:
            measured["throughput"] = child_throughput(args.run_dir, args.throughput_map, out, str(device))
        print_child_result(measured)
        return None

    width, scales, throughput_scale = WIDTH, SCALES, THROUGHPUT_SCALE
    if args.quick:
        width, scales, throughput_scale = QUICK["width"], QUICK["scales"], QUICK["throughput_scale"]
    flags = [f"--device={args.device}", f"--cache-dir={folder.parent}"]
    rows: list[dict[str, Any]] = []
    peaks: list[float] = []
    throughput: dict[str, Any] = {}
    for scale in scales:
        episodes = BASE_EPISODES * scale
        run_dir = write_run(folder / f"run-w{width}-x{scale}", episodes, width)
        fixed = write_map(folder / f"map-fixed-x{scale}.json", list(range(BASE_EPISODES)), SEGMENT_FRAMES,
                          episodes * FRAMES_PER_EPISODE)
        child = [*flags, "--child", f"--run-dir={run_dir}", f"--concept-map={fixed}"]
        if scale == throughput_scale:  # the same process measures throughput after its memory peak
            every_row = write_map(folder / f"map-all-x{scale}.json", list(range(episodes)),
                                  (0, FRAMES_PER_EPISODE - 1), episodes * FRAMES_PER_EPISODE)
            child.append(f"--throughput-map={every_row}")
        measured = run_child("slicing_memory", child)
        peaks.append(measured["peak_rss_mib"])
        rows.append(_row(f"{scale}x run, fixed pair", episodes, measured))
        if "throughput" in measured:
            throughput = measured["throughput"]
            rows.append(_row(f"{scale}x run, every row sliced", episodes, throughput))
    spread = max(peaks) / min(peaks)
    megabytes = throughput["shard_bytes"] / 2**20
    slicing_rate, read_rate = megabytes / throughput["seconds"], megabytes / throughput["read_seconds"]
    floor_rate = megabytes / throughput["floor_seconds"]
    result = Result(
        name="slicing",
        title="3. Slicing memory and throughput",
        command=command("slicing_memory", args),
        measured=f"{slicing_rate:,.0f} MiB/s; peak RSS {min(peaks):.0f}-{max(peaks):.0f} MiB over "
                 f"{scales[0]}x-{scales[-1]}x ({spread:.2f}x)",
        baseline=f"read + write x2 {floor_rate:,.0f} MiB/s",
        ratio=slicing_rate / floor_rate,
        target=f">= {THROUGHPUT_TARGET}x of read + write x2, and peak RSS flat within {TARGET}x",
        met=slicing_rate / floor_rate >= THROUGHPUT_TARGET and spread <= TARGET,
        table=rows,
        checks={"peak_rss_spread": spread, "slicing_vs_plain_read": slicing_rate / read_rate},
        notes=[
            f"runs: {BASE_EPISODES} x scale episodes of {FRAMES_PER_EPISODE} frames x {TOKENS_PER_FRAME} tokens, "
            f"width {width}, float32, one shard per episode; each measurement in a fresh process (VmHWM).",
            f"fixed pair: 2 concepts, frames {SEGMENT_FRAMES[0]}-{SEGMENT_FRAMES[1]} of the first {BASE_EPISODES} "
            "episodes, the same in every run; 'RSS before' is the process after imports, before slicing.",
            f"throughput ({throughput_scale}x run, every row sliced, best of {ROUNDS} after a warm-up, page cache "
            f"warm): slicing {slicing_rate:.0f} MiB/s of shard bytes vs a plain sequential read {read_rate:.0f} MiB/s "
            f"= {slicing_rate / read_rate:.3f}x, and vs reading the shards and writing their bytes twice (slicing "
            f"writes every row to a .pt and a .safetensors) {floor_rate:.0f} MiB/s = {slicing_rate / floor_rate:.2f}x.",
            "how: the first pass reads only the shards' row columns (one read each) and chooses rows; the second "
            "reads each shard once, front to back through one 8 MiB buffer, feeding its bytes to the shard's CRC-32 "
            "check (ISA-L) and writing the selected rows straight to their offsets in each concept's .safetensors "
            "(os.pwrite), whose data CRC-32 grows as rows arrive in order; torch.save then writes the .pt from a "
            "memory map of that file with torch's own CRC-32 off and the known CRC-32s filled in "
            "(steering_core/capture/slice_copy.py, shard_checks.py, slice_files.py). One thread; the floor does no "
            "hashing.",
        ],
    )
    return finish(result, args)


def _row(case: str, episodes: int, measured: dict[str, Any]) -> dict[str, Any]:
    """Return one table row from a child measurement (rates only where every row is sliced)."""
    megabytes = measured["shard_bytes"] / 2**20
    throughput = "read_seconds" in measured
    return {
        "case": case,
        "episodes": episodes,
        "shard MiB": megabytes,
        "RSS before MiB": measured.get("rss_before_mib", ""),
        "peak RSS MiB": measured.get("peak_rss_mib", ""),
        "slicing working set MiB": measured["peak_rss_mib"] - measured["rss_before_mib"] if not throughput else "",
        "slice s": measured["seconds"],
        "slice MiB/s": megabytes / measured["seconds"] if throughput else "",
        "plain read MiB/s": megabytes / measured["read_seconds"] if throughput else "",
        "read + write x2 MiB/s": megabytes / measured["floor_seconds"] if throughput else "",
    }


if __name__ == "__main__":
    main()
