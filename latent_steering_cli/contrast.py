"""`latent-steering manifest` and `latent-steering concept-map`: the contrast half of phase 1."""

from __future__ import annotations

from pathlib import Path

import typer

from latent_steering_cli.app import app, input_errors
from latent_steering_cli.numbers import number_option
from steering_core.data.concept_map import build_concept_map, read_rename_map, write_concept_map
from steering_core.data.contrast import MAX_EPISODES, ContrastSettings, build_manifest, write_manifest
from steering_core.data.contrast_hdf5 import build_hdf5_manifest
from steering_core.data.convert import DemoOrder
from steering_core.storage.overwrites import check_no_overwrite

_DEFAULTS = ContrastSettings()



def _episode_list(values: list[str] | None, flag: str) -> tuple[int, ...] | None:
    """Return the episode indices of repeated/comma-separated values with ranges, e.g. `0-4,7`."""
    if not values:
        return None
    spans: list[range] = []
    for part in ",".join(values).split(","):
        part = part.strip()
        try:
            low, high = (int(p) for p in part.split("-", 1)) if "-" in part else (int(part),) * 2
            if high < low:
                raise ValueError
        except ValueError:
            raise typer.BadParameter(f"{part!r} is not an episode index or range like 3-7", param_hint=flag) from None
        spans.append(range(low, high + 1))
    if (count := sum(len(span) for span in spans)) > MAX_EPISODES:  # counted as ranges, before any is expanded
        raise typer.BadParameter(f"{count:,} episode indices; expected at most {MAX_EPISODES:,} (a dataset's episodes "
                                 "number in the thousands)", param_hint=flag)
    return tuple(index for span in spans for index in span)


def _task(text: str | None, index: int | None, letter: str) -> str | int:
    """Return task A's or B's text or index from its two flags (exactly one must be given)."""
    if (text is None) == (index is None):
        raise typer.BadParameter(
            f"give exactly one of --task-{letter}-text and --task-{letter}-index", param_hint=f"--task-{letter}-text"
        )
    return text if text is not None else index


@app.command("manifest")
def manifest_command(
    lerobot_root: Path | None = typer.Option(
        None, "--lerobot-root", help="LeRobot dataset folder (v3.0, v2.1 or v2.0); the lerobot backend."
    ),
    task_a_text: str | None = typer.Option(None, "--task-a-text", help="Task A's instruction (e.g. the 'open' task)."),
    task_b_text: str | None = typer.Option(None, "--task-b-text", help="Task B's instruction (e.g. the 'close' task)."),
    task_a_index: int | None = typer.Option(None, "--task-a-index", help="Task A by its dataset task_index."),
    task_b_index: int | None = typer.Option(None, "--task-b-index", help="Task B by its dataset task_index."),
    task_a_label: str | None = typer.Option(
        None, "--task-a-label", help="Name recorded for task A (segments, concepts); default its instruction."
    ),
    task_b_label: str | None = typer.Option(None, "--task-b-label", help="Name recorded for task B."),
    backend: str = typer.Option(
        "lerobot", "--backend", help="lerobot (a converted dataset) or hdf5 (two LIBERO task files, as the seed could)."
    ),
    task_a_file: Path | None = typer.Option(None, "--task-a-file", help="hdf5 backend: task A's LIBERO .hdf5 file."),
    task_b_file: Path | None = typer.Option(None, "--task-b-file", help="hdf5 backend: task B's LIBERO .hdf5 file."),
    search_root: Path | None = typer.Option(
        None, "--search-root", help="hdf5 backend: folder the task files are looked up in (by path, then by name)."
    ),
    demo_order: DemoOrder = typer.Option(
        "numeric", "--demo-order", help="hdf5 backend: numeric, or lexicographic (the seed's: demo_10 before demo_2)."
    ),
    output: Path = typer.Option(..., "--output", help="Manifest JSON to write (data/manifests/<pair>.json)."),
    repo_id: str | None = typer.Option(None, "--repo-id", help="Recorded repo id (default: the dataset folder name)."),
    min_abs_delta: float = number_option(
        _DEFAULTS.min_abs_delta, "--min-abs-delta", help="Least |mean terminal displacement| per task on the axis."
    ),
    progress_frac: float = number_option(
        _DEFAULTS.progress_frac, "--progress-frac", help="Share of a demo's axis displacement that opens its window."
    ),
    pad: int = typer.Option(_DEFAULTS.pad, "--pad", help="Frames added on both sides of each window."),
    max_demos_per_task: int | None = typer.Option(
        None, "--max-demos-per-task", help="Use only the first N demos (by episode index) of each task."
    ),
    task_a_episodes: list[str] | None = typer.Option(
        None, "--task-a-episodes", help="Episodes of task A to use, e.g. 0-9,12 (repeatable)."
    ),
    task_b_episodes: list[str] | None = typer.Option(
        None, "--task-b-episodes", help="Episodes of task B to use (repeatable)."
    ),
    segments_per_class: int | None = typer.Option(
        None, "--segments-per-class", help="Keep the N segments per task that progress furthest along the axis."
    ),
) -> None:
    """Find the state axis two tasks move along in opposite directions and each demo's window on it."""
    if backend not in ("lerobot", "hdf5"):
        raise typer.BadParameter(f"{backend!r}: expected lerobot or hdf5", param_hint="--backend")
    if backend == "hdf5" and (task_a_file is None or task_b_file is None):
        raise typer.BadParameter("the hdf5 backend needs --task-a-file and --task-b-file", param_hint="--task-a-file")
    if backend == "lerobot" and lerobot_root is None:
        raise typer.BadParameter("the lerobot backend needs --lerobot-root", param_hint="--lerobot-root")
    with input_errors():
        check_no_overwrite({"--output": output}, {"--lerobot-root": lerobot_root, "--task-a-file": task_a_file,
                                                  "--task-b-file": task_b_file, "--search-root": search_root})
        settings = ContrastSettings(
            min_abs_delta=min_abs_delta,
            progress_frac=progress_frac,
            pad=pad,
            max_demos_per_task=max_demos_per_task,
            task_a_episodes=_episode_list(task_a_episodes, "--task-a-episodes"),
            task_b_episodes=_episode_list(task_b_episodes, "--task-b-episodes"),
            segments_per_class=segments_per_class,
            task_a_label=task_a_label,
            task_b_label=task_b_label,
        )
        if backend == "hdf5":
            manifest = build_hdf5_manifest(task_a_file, task_b_file, settings, search_root=search_root,
                                           demo_order=demo_order)
        else:
            task_a, task_b = _task(task_a_text, task_a_index, "a"), _task(task_b_text, task_b_index, "b")
            manifest = build_manifest(lerobot_root, task_a, task_b, settings, repo_id=repo_id)
        write_manifest(manifest, output)
    means = ", ".join(f"{task!r} {mean:+.4f}" for task, mean in manifest.axis.mean_delta_per_task.items())
    typer.echo(f"wrote {output}")
    typer.echo(f"axis {manifest.axis.index}, effect size {manifest.axis.effect_size:.3f} (mean delta: {means})")
    for task in manifest.axis.mean_delta_per_task:
        count = sum(seg.task == task for seg in manifest.segments)
        typer.echo(f"  {task!r}: {count} segment(s)")


@app.command("concept-map")
def concept_map_command(
    manifest_path: Path = typer.Option(..., "--manifest-path", help="Contrast manifest JSON."),
    output_path: Path = typer.Option(..., "--output-path", help="Concept map JSON to write."),
    lerobot_root: Path = typer.Option(..., "--lerobot-root", help="The LeRobot dataset the manifest was built from."),
    repo_id: str | None = typer.Option(None, "--repo-id", help="Recorded repo id (default: the dataset folder name)."),
    concept_map: Path | None = typer.Option(
        None, "--concept-map", help="JSON object renaming task texts to concept names."
    ),
) -> None:
    """Map every manifest segment to its global dataset indices, grouped by concept."""
    with input_errors():
        check_no_overwrite({"--output-path": output_path}, {"--manifest-path": manifest_path,
                                                            "--lerobot-root": lerobot_root, "--concept-map": concept_map})
        rename = read_rename_map(concept_map) if concept_map is not None else None
        result = build_concept_map(manifest_path, lerobot_root, repo_id=repo_id, rename=rename)
        write_concept_map(result, output_path)
    typer.echo(f"wrote {output_path} ({result.sample_count} frames in the dataset)")
    for concept, rows in result.concepts.items():
        typer.echo(f"  {concept!r}: {len(rows)} segment(s), {sum(r.length for r in rows)} sample(s)")
