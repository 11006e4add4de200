"""CLI commands of phase 1 (preparing data): `filter`, `convert`, and `make-demos` for synthetic inputs."""

from __future__ import annotations

from pathlib import Path

import typer

from latent_steering_cli.app import app, input_errors
from steering_core.data.convert import (
    CodebaseVersion,
    ConvertSettings,
    DemoOrder,
    Orientation,
    ResizeFilter,
    convert_libero,
)
from steering_core.data.filtering import FilterSettings, filter_demos
from steering_core.storage.overwrites import check_no_overwrite
from steering_core.synthetic.libero import SyntheticSettings, write_demo_suite

_CONVERT_DEFAULTS = ConvertSettings(repo_id="-")


@app.command("filter")
def filter_command(
    input_dir: list[Path] = typer.Option(..., "--input-dir", help="Folder of LIBERO *_demo.hdf5 files (repeatable)."),
    output_dir: Path = typer.Option(
        ..., "--output-dir", help="Filtered folder to (re)write, e.g. data/libero_filtered/open_close."
    ),
    task: list[str] = typer.Option([], "--task", help="Select files whose instruction is this text (repeatable)."),
    glob: list[str] = typer.Option([], "--glob", help="Select files whose name matches this glob (repeatable)."),
    copy: bool = typer.Option(False, "--copy", help="Copy the files instead of symlinking them."),
    exact: bool = typer.Option(False, "--exact", help="Match task text exactly (default: ignore case and spacing)."),
) -> None:
    """Select demo files by task text or file-name glob into a folder with selection.json."""
    settings = FilterSettings(
        tasks=tuple(task),
        globs=tuple(glob),
        match="exact" if exact else "ignore_case",
        mode="copy" if copy else "symlink",
    )
    with input_errors():
        check_no_overwrite({"--output-dir": output_dir}, {"--input-dir": input_dir})
        selection = filter_demos(input_dir, output_dir, settings)
    for entry in selection.files:
        typer.echo(f"{entry.name}\t{entry.num_demos} demos\t{entry.instruction}")
    typer.echo(f"{len(selection.files)} file(s) in {output_dir}")


@app.command("convert")
def convert_command(
    input_dir: list[Path] = typer.Option(..., "--input-dir", help="Folder of LIBERO *.hdf5 files (repeatable)."),
    repo_id: str = typer.Option(
        ..., "--repo-id", help="LeRobot repo id recorded in the dataset, e.g. libero_open_close_lerobot."
    ),
    output_dir: Path = typer.Option(..., "--output-dir", help="Dataset folder, e.g. data/libero_lerobot/<repo_id>."),
    image_size: int = typer.Option(
        256, "--image-size", help="Square frame size (physical-intelligence/libero: 256)."
    ),
    orientation: Orientation = typer.Option(
        "rotate180",
        "--orientation",
        help="rotate180 (what pi05_libero was trained on) or as_stored (raw renders).",
    ),
    append: bool = typer.Option(
        True, "--append/--rebuild", help="Append only new demos to an existing dataset when possible, or rebuild it."
    ),
    fps: int = typer.Option(_CONVERT_DEFAULTS.fps, "--fps", min=1, help="Declared frame rate (openpi's LIBERO: 10)."),
    codebase_version: CodebaseVersion = typer.Option(
        _CONVERT_DEFAULTS.codebase_version, "--codebase-version",
        help="v3.0 (lerobot 0.4) or v2.1 (openpi's pinned lerobot, laid out as openpi's LIBERO conversion).",
    ),
    resize_filter: ResizeFilter = typer.Option(
        _CONVERT_DEFAULTS.resize_filter, "--resize-filter",
        help="antialiased_bilinear (openpi's resize) or bicubic (PIL, as the seed's converter upsampled 128 -> 256).",
    ),
    demo_order: DemoOrder = typer.Option(
        _CONVERT_DEFAULTS.demo_order, "--demo-order",
        help="numeric (demo_2 before demo_10) or lexicographic (the seed's sorted(keys): demo_10 before demo_2).",
    ),
) -> None:
    """Convert LIBERO demos into a LeRobot dataset (openpi's physical-intelligence/libero schema)."""
    with input_errors():
        check_no_overwrite({"--output-dir": output_dir}, {"--input-dir": input_dir})
        settings = ConvertSettings(repo_id=repo_id, image_size=image_size, orientation=orientation, fps=fps,
                                   codebase_version=codebase_version, resize_filter=resize_filter,
                                   demo_order=demo_order)
        result = convert_libero(input_dir, output_dir, settings, rebuild=not append)
    typer.echo(
        f"{result.action}: {result.root} holds {result.episodes_total} episodes ({result.frames_total} frames), "
        f"{result.episodes_added} added"
    )


@app.command("make-demos")
def make_demos_command(
    output_dir: Path = typer.Option(..., "--output-dir", help="Folder to write the synthetic LIBERO files into."),
    image_size: int = typer.Option(128, "--image-size", help="Square render size (LIBERO: 128)."),
    demos_per_task: int = typer.Option(4, "--demos-per-task", min=1, help="Demos per task file."),
    num_steps: int = typer.Option(60, "--num-steps", help="Steps per demo (real LIBERO demos: 100-300)."),
    seed: int = typer.Option(0, "--seed", help="Seed of the small deterministic noise."),
) -> None:
    """Write synthetic LIBERO demos for two concept pairs (drawer open/close, stove on/off)."""
    with input_errors():
        # a little length variation, as real demos have
        settings = SyntheticSettings(
            image_size=image_size, num_steps=num_steps, length_jitter=num_steps // 10, seed=seed
        )
        files = write_demo_suite(output_dir, demos_per_task=demos_per_task, settings=settings)
    for written in files:
        typer.echo(f"{written.path}\t{len(written.demos)} demos\t{written.instruction}")
