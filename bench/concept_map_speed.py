"""Concept map: our index-column mapping against the seed's row-by-row walk over a LeRobot dataset.

Ours is `steering_core.data.concept_map.build_concept_map`: manifest segments found by binary search over the
dataset's integer index columns, read from parquet without touching a frame. The seed's
`map_concept_samples.py` iterated every row of the LeRobotDataset (`dataset.hf_dataset`), which decodes
both camera images of each frame, to learn each row's episode and frame index. Both map the same manifest
on the same dataset of 20,000 frames, generated once through the library's own path (synthetic LIBERO demo
files -> `convert_libero`) with 8 x 8 images so that it is quick to build; real 256 x 256 frames would
make the seed's walk much slower and leave ours unchanged.

    uv run python -m bench.concept_map_speed [--device cuda] [--quick]
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from bench.common import (
    Result,
    cache_dir,
    command,
    finish,
    median,
    parser,
    repeat_timed,
    timed,
)
from steering_core.devices import resolve_device

# ----------------------------------------------------------------------------- settings

TASKS = 4  # the synthetic demo suite: drawer open/close, stove on/off
DEMOS_PER_TASK = 5
STEPS_PER_DEMO = 1000  # 4 x 5 x 1000 = 20,000 frames
IMAGE_SIZE = 8  # pixels per side of both cameras: small, so the dataset builds in about 20 s
REPEATS = 5  # timed calls of ours (median kept); the seed's walk is timed once, over every row
TARGET = 100.0  # ours / seed frames/s

QUICK = {"demos_per_task": 2, "steps_per_demo": 20}


def build_dataset(folder: Path, demos_per_task: int, steps: int) -> tuple[Path, str, Path]:
    """Return (dataset root, repo id, manifest path) of the drawer pair, generating what is not cached yet."""
    from steering_core.data.contrast import build_manifest, write_manifest
    from steering_core.data.convert import ConvertSettings, convert_libero
    from steering_core.synthetic.libero import DRAWER_CLOSE, DRAWER_OPEN, SyntheticSettings, write_demo_suite

    frames = TASKS * demos_per_task * steps
    demos = folder / f"libero-{frames}"
    if not demos.is_dir():
        write_demo_suite(demos, demos_per_task=demos_per_task,
                         settings=SyntheticSettings(image_size=IMAGE_SIZE, num_steps=steps))
    repo_id = f"bench/concept-map-{frames}"
    root = folder / f"lerobot-{frames}"
    convert_libero([demos], root, ConvertSettings(repo_id=repo_id, image_size=IMAGE_SIZE))  # no-op once built
    manifest = folder / f"manifest-{frames}.json"
    if not manifest.is_file():
        write_manifest(build_manifest(root, DRAWER_OPEN, DRAWER_CLOSE), manifest)
    return root, repo_id, manifest


def seed_concept_map(manifest_path: Path, root: Path, repo_id: str) -> dict[str, list[dict[str, int]]]:
    """Return concept -> [{segment_id, episode_index, start_index, end_index}] by walking every dataset row.

    The seed's method: open the LeRobotDataset and iterate its rows in order (each row's images are
    decoded), counting the global position and noting where each manifest segment starts and ends.
    """
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    from steering_core.data.contrast import read_manifest

    manifest = read_manifest(manifest_path)
    by_episode: dict[int, list[tuple[int, int, int]]] = {}
    for number, segment in enumerate(manifest.segments):
        by_episode.setdefault(segment.episode_index, []).append((number, segment.start_step, segment.end_step))
    found: dict[int, list[int]] = {}
    dataset = LeRobotDataset(repo_id, root=root)
    for position, row in enumerate(dataset.hf_dataset):
        frame = int(row["frame_index"])
        for number, start, end in by_episode.get(int(row["episode_index"]), ()):
            if start <= frame <= end:
                found.setdefault(number, [position, position])[1] = position
    concepts: dict[str, list[dict[str, int]]] = {}
    for number, (first, last) in sorted(found.items(), key=lambda item: item[1][0]):
        segment = manifest.segments[number]
        concepts.setdefault(segment.task, []).append(
            {"segment_id": number, "episode_index": segment.episode_index, "start_index": first, "end_index": last}
        )
    return concepts


def same_mapping(ours: Any, seed: dict[str, list[dict[str, int]]]) -> bool:
    """Return whether both methods found the same index range for every segment of every concept."""
    fields = ("segment_id", "episode_index", "start_index", "end_index")
    mine = {concept: [{k: getattr(row, k) for k in fields} for row in rows] for concept, rows in ours.concepts.items()}
    return mine == seed


def main(argv: list[str] | None = None) -> Result:
    """Run the benchmark; return (and print) its result."""
    args = parser(__doc__.splitlines()[0]).parse_args(argv)
    device = resolve_device(args.device)  # both sides are CPU work; the flag is accepted for uniformity
    demos_per_task, steps = DEMOS_PER_TASK, STEPS_PER_DEMO
    if args.quick:
        demos_per_task, steps = QUICK["demos_per_task"], QUICK["steps_per_demo"]
    root, repo_id, manifest = build_dataset(cache_dir(args) / "concept_map", demos_per_task, steps)

    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    from steering_core.data.concept_map import build_concept_map

    LeRobotDataset(repo_id, root=root)  # warm-up: builds the datasets library's Arrow cache once
    ours_times = repeat_timed(lambda: build_concept_map(manifest, root), device, warmup=1, repeats=REPEATS)
    ours = build_concept_map(manifest, root)
    seed, seed_time = timed(lambda: seed_concept_map(manifest, root, repo_id), device)
    frames = ours.sample_count
    ours_time = median(ours_times)
    ratio = seed_time / ours_time
    rows = [
        {"method": "ours: index columns + binary search", "frames": frames, "seconds": ours_time,
         "frames/s": frames / ours_time, "ratio": ratio},
        {"method": "seed: walk every LeRobotDataset row", "frames": frames, "seconds": seed_time,
         "frames/s": frames / seed_time, "ratio": 1.0},
    ]
    result = Result(
        name="concept_map",
        title="2. Concept map (manifest segments -> dataset indices)",
        command=command("concept_map_speed", args),
        measured=f"{frames / ours_time:,.0f} frames/s",
        baseline=f"{frames / seed_time:,.0f} frames/s",
        ratio=ratio,
        target=f">= {TARGET:.0f}x",
        met=ratio >= TARGET,
        table=rows,
        notes=[
            f"{frames} frames ({TASKS} tasks x {demos_per_task} demos x {steps} steps), {IMAGE_SIZE} x {IMAGE_SIZE} "
            f"PNG cameras; manifest: drawer open vs close, {sum(len(v) for v in ours.concepts.values())} segments.",
            f"ours: median of {REPEATS} calls after a warm-up, from the files (manifest, metadata, index columns); "
            "seed: one timed walk over every row, dataset open included.",
            f"identical index ranges for every segment: {same_mapping(ours, seed)}.",
        ],
        checks={"same_mapping": same_mapping(ours, seed), "frames": frames},
    )
    return finish(result, args)


if __name__ == "__main__":
    main()
