"""`latent-steering manifest` and `latent-steering concept-map`: the contrast half of phase 1."""

from __future__ import annotations

from pathlib import Path

import typer

from cli.app import app, input_errors
from steering_core.data.concept_map import (
    build_concept_map,
    read_rename_map,
    write_concept_map,
)
from steering_core.data.contrast import ContrastSettings, build_manifest, write_manifest

_DEFAULTS = ContrastSettings()



def _episode_list(values: list[str] | None, flag: str) -> tuple[int, ...] | None:
    """Return the episode indices of repeated/comma-separated values with ranges, e.g. `0-4,7`."""
    if not values:
        return None
    indices: list[int] = []
    for part in ",".join(values).split(","):
        part = part.strip()
        try:
            if "-" in part:
                low, high = (int(p) for p in part.split("-", 1))
                if high < low:
                    raise ValueError
                indices.extend(range(low, high + 1))
            else:
                indices.append(int(part))
        except ValueError:
            raise typer.BadParameter(f"{part!r} is not an episode index or range like 3-7", param_hint=flag) from None
    return tuple(indices)


@app.command("manifest")
def manifest_command(
    lerobot_root: Path = typer.Option(..., "--lerobot-root", help="LeRobot v3.0 dataset folder."),
    task_a_text: str = typer.Option(..., "--task-a-text", help="Task A's instruction (e.g. the 'open' task)."),
    task_b_text: str = typer.Option(..., "--task-b-text", help="Task B's instruction (e.g. the 'close' task)."),
    output: Path = typer.Option(..., "--output", help="Manifest JSON to write (data/manifests/<pair>.json)."),
    repo_id: str | None = typer.Option(None, "--repo-id", help="Recorded repo id (default: the dataset folder name)."),
    min_abs_delta: float = typer.Option(
        _DEFAULTS.min_abs_delta, "--min-abs-delta", help="Least |mean terminal displacement| per task on the axis."
    ),
    progress_frac: float = typer.Option(
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
    with input_errors():
        settings = ContrastSettings(
            min_abs_delta=min_abs_delta,
            progress_frac=progress_frac,
            pad=pad,
            max_demos_per_task=max_demos_per_task,
            task_a_episodes=_episode_list(task_a_episodes, "--task-a-episodes"),
            task_b_episodes=_episode_list(task_b_episodes, "--task-b-episodes"),
            segments_per_class=segments_per_class,
        )
        manifest = build_manifest(lerobot_root, task_a_text, task_b_text, settings, repo_id=repo_id)
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
        rename = read_rename_map(concept_map) if concept_map is not None else None
        result = build_concept_map(manifest_path, lerobot_root, repo_id=repo_id, rename=rename)
        write_concept_map(result, output_path)
    typer.echo(f"wrote {output_path} ({result.sample_count} frames in the dataset)")
    for concept, rows in result.concepts.items():
        typer.echo(f"  {concept!r}: {len(rows)} segment(s), {sum(r.length for r in rows)} sample(s)")
