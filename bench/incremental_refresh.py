"""Incremental refresh: the scheduled refresh after one demo file is added to ten, against a run from scratch.

Both go through the Prefect flows in this process, on an embedded server started before any timing, with
the `latent-steering demo` model side (tiny pi0.5, tokenizer and one SAE per layer, two concept pairs) and
ten LIBERO files of the pairs' four tasks (the four task files plus six more scenes of the same tasks),
converted at the real 256 x 256 dataset size. A warm-up runs the whole pipeline once on a separate small
demo, so that imports and other first-call costs are paid before timing. The baseline is the first run,
the whole pipeline from scratch on the ten files (`flows.refresh.refresh` with no record of a success).
Then an eleventh file (another scene of "open the top drawer of the cabinet") is added and the refresh
is timed: it hashes the new file, appends its episodes to the dataset, captures only them, and recomputes
only the pair they belong to. A from-scratch run on all eleven files would take a little longer than the
baseline, so the ratio is conservative. Both runs include phase 4, the steering evaluation (the demo's small
settings): evaluating a pair costs the same whatever its data size, so the refresh re-evaluates the changed
pair in full and reads every other evaluation from the cache; the result counts the evaluations it redid.

    uv run python -m bench.incremental_refresh [--device cuda] [--quick]
"""

from __future__ import annotations

import shutil
from pathlib import Path

import torch

from bench.common import (
    Result,
    cache_dir,
    command,
    finish,
    parser,
    timed,
)
from steering_core.devices import resolve_device

# ----------------------------------------------------------------------------- settings

BASE_FILES = 10  # demo files before the refresh
DEMOS_PER_FILE = 4  # LIBERO files hold 50; enough here for the per-file work to outweigh fixed costs
STEPS_PER_DEMO = 80  # real demos: 100-300 steps
SOURCE_IMAGE_SIZE = 128  # LIBERO's render size in the demo files
DATASET_IMAGE_SIZE = 256  # physical-intelligence/libero's frame size (the convert default)
EXTRA_SCENE_START = 11  # scene numbers of the generated extra files: KITCHEN_SCENE11, 12, ...
ADDED_SCENE = 30  # scene of the eleventh file
WARM_UP_DEMOS = 2  # demos per task of the warm-up pipeline run
TARGET = 0.20  # refresh time / from-scratch time, at most

QUICK = {"base_files": 4, "demos_per_file": 2, "steps": 12, "image_size": 32, "warm_up": False}


def demo_settings(steps: int, seed: int = 0):
    """Return the synthetic LIBERO settings of the benchmark's demo files."""
    from steering_core.synthetic.libero import SyntheticSettings

    return SyntheticSettings(image_size=SOURCE_IMAGE_SIZE, num_steps=steps, seed=seed)


def build_inputs(folder: Path, base_files: int, demos_per_file: int, steps: int, image_size: int,
                 device: torch.device) -> tuple[Path, Path]:
    """Return (run config, demo folder): the demo's model side with `base_files` demo files of our sizes."""
    from steering_core.config import load_run_config, write_run_config
    from steering_core.demo import build_demo
    from steering_core.synthetic.libero import DEMO_SUITE_TASKS, SyntheticTask, write_libero_file

    shutil.rmtree(folder, ignore_errors=True)  # every run starts from the same ten files and no outputs
    config_path = build_demo(folder, demos_per_task=demos_per_file)
    config = load_run_config(config_path)
    demos = config.sources.folders[0]
    shutil.rmtree(demos)  # the demo's own small files, replaced by files of the benchmark's sizes
    for number in range(base_files):
        task = DEMO_SUITE_TASKS[number % len(DEMO_SUITE_TASKS)]
        if number >= len(DEMO_SUITE_TASKS):
            scene = f"KITCHEN_SCENE{EXTRA_SCENE_START + number - len(DEMO_SUITE_TASKS)}"
            task = SyntheticTask(instruction=task.instruction, scene=scene, motion=task.motion)
        write_libero_file(demos, task, num_demos=demos_per_file, settings=demo_settings(steps))
    write_run_config(config.model_copy(update={
        # the borrowed SAEs only: an SAE retrained on the added demos' rows would change every pair's vectors at
        # its layer, while this measures what an added demo file recomputes of capture, SAE phase and evaluation
        "sae": {layer: sae.model_copy(update={"train": None}) for layer, sae in config.sae.items()},
        "evaluate": config.evaluate.model_copy(update={"device": str(device)}),
        "dataset": config.dataset.model_copy(update={"image_size": image_size}),
        "capture": config.capture.model_copy(update={"device": str(device)}),
        "steering": config.steering.model_copy(update={"device": str(device)}),
    }), config_path)
    return config_path, demos


def add_file(demos: Path, demos_per_file: int, steps: int) -> Path:
    """Write the eleventh demo file (another scene of the first task) into the demo folder; return it."""
    from steering_core.synthetic.libero import DEMO_SUITE_TASKS, SyntheticTask, write_libero_file

    task = DEMO_SUITE_TASKS[0]
    scene = SyntheticTask(instruction=task.instruction, scene=f"KITCHEN_SCENE{ADDED_SCENE}", motion=task.motion)
    return write_libero_file(demos, scene, num_demos=demos_per_file, settings=demo_settings(steps, seed=1)).path


def shard_digests(config_path: Path) -> dict[str, str]:
    """Return shard file -> sha256 of a finished run, from its metadata."""
    from steering_core.capture.shards import read_run_metadata
    from steering_core.config import load_run_config

    return {record.file: record.sha256 for record in read_run_metadata(load_run_config(config_path).run_dir).shards}


def evaluation_stamps(config_path: Path) -> dict[Path, int]:
    """Return dose_response.json -> modification time (ns) of every evaluation the run wrote."""
    from steering_core.config import load_run_config
    from steering_core.layout import DOSE_RESPONSE_FILE

    root = load_run_config(config_path).eval_root
    return {path: path.stat().st_mtime_ns for path in root.glob(f"*/*/{DOSE_RESPONSE_FILE}.json")}


def main(argv: list[str] | None = None) -> Result:
    """Run the benchmark; return (and print) its result."""
    args = parser(__doc__.splitlines()[0]).parse_args(argv)
    device = resolve_device(args.device)
    base_files, demos_per_file, steps, image_size, warm = (
        BASE_FILES, DEMOS_PER_FILE, STEPS_PER_DEMO, DATASET_IMAGE_SIZE, True)
    if args.quick:
        base_files, demos_per_file, steps, image_size, warm = (
            QUICK["base_files"], QUICK["demos_per_file"], QUICK["steps"], QUICK["image_size"], QUICK["warm_up"])
    folder = cache_dir(args) / "refresh"

    from latent_steering_cli.run import prefect_environment

    prefect_environment(home=folder.parent / "prefect-home")  # before Prefect is imported
    from prefect import flow

    from flows.refresh import refresh
    from steering_core.demo import build_demo

    @flow(name="bench-warm-up")
    def start_server() -> None:
        """Start Prefect's embedded server, so that no timed run pays for it."""

    start_server()
    if warm:  # imports, code fingerprints and first calls, paid once before timing
        shutil.rmtree(folder / "warm-up", ignore_errors=True)
        refresh(str(build_demo(folder / "warm-up", demos_per_task=WARM_UP_DEMOS)))
    config, demos = build_inputs(folder / "run", base_files, demos_per_file, steps, image_size, device)
    first, scratch_seconds = timed(lambda: refresh(str(config)), device)
    before, evaluated = shard_digests(config), evaluation_stamps(config)
    add_file(demos, demos_per_file, steps)
    refreshed, refresh_seconds = timed(lambda: refresh(str(config)), device)
    after = shard_digests(config)
    redone = sum(evaluation_stamps(config).get(path) != stamp for path, stamp in evaluated.items())
    untouched = all(after.get(file) == digest for file, digest in before.items())
    added = len(after) - len(before)
    ratio = refresh_seconds / scratch_seconds
    frames = base_files * demos_per_file * steps
    rows = [
        {"run": f"from scratch, {base_files} files ({frames} frames)", "seconds": scratch_seconds,
         "pipeline ran": first["ran"]},
        {"run": f"refresh after adding file {base_files + 1} ({demos_per_file * steps} frames)",
         "seconds": refresh_seconds, "pipeline ran": refreshed["ran"]},
    ]
    result = Result(
        name="refresh",
        title=f"5. Incremental refresh (1 demo file added to {base_files})",
        command=command("incremental_refresh", args),
        measured=f"refresh {refresh_seconds:.1f} s",
        baseline=f"from scratch {scratch_seconds:.1f} s",
        ratio=ratio,
        target=f"<= {TARGET:.0%} of from scratch",
        met=ratio <= TARGET,
        table=rows,
        checks={"old_shards_untouched": untouched, "shards_added": added, "refresh_ran": refreshed["ran"],
                "changes": refreshed["changes"], "evaluations": len(evaluated), "evaluations_redone": redone},
        notes=[
            f"{base_files} + 1 LIBERO files of {demos_per_file} demos x {steps} steps, {image_size} px dataset "
            f"frames, 2 pairs, layers {', '.join(map(str, _layers(config)))}, tiny pi0.5 on {device.type}; flows in "
            "this process on Prefect's embedded server; the ratio is refresh / from scratch (lower is better).",
            f"the refresh saw: {refreshed['changes']}; it wrote {added} new shard file(s) and left every existing "
            f"shard byte-identical: {untouched}.",
            f"both runs include the steering evaluation ({len(evaluated)} (pair, layer) evaluations); the refresh "
            f"redid {redone} of them (those of the pair the new file belongs to) and read the others from the cache.",
        ],
    )
    return finish(result, args)


def _layers(config_path: Path) -> tuple[int, ...]:
    """Return the run config's layers."""
    from steering_core.config import load_run_config

    return load_run_config(config_path).layers


if __name__ == "__main__":
    main()
