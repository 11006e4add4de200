"""`latent-steering capture` and `latent-steering slice`: phase 2 of the seed pipeline."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from enum import Enum
from pathlib import Path

import typer

from steering_core.cli.app import app
from steering_core.slicing import SliceSettings, slice_concepts


class ReduceChoice(str, Enum):
    """Rows per captured frame in a slice."""

    token = "token"
    frame = "frame"


class TokenTypeChoice(str, Enum):
    """Which prompt tokens a capture keeps (see steering_core.capture)."""

    instructions = "instructions"
    prompt = "prompt"
    last = "last"


@contextlib.contextmanager
def _input_errors() -> Iterator[None]:
    """Turn bad-input errors of the library into a one-line message and exit code 1."""
    try:
        yield
    except (ValueError, FileNotFoundError) as err:
        typer.echo(f"error: {err}", err=True)
        raise typer.Exit(1) from None


def _layer_list(value: str, flag: str = "--layers") -> tuple[int, ...]:
    """Return the layers of a comma- or space-separated list, e.g. `12` or `6,12`."""
    try:
        layers = tuple(int(part) for part in value.replace(",", " ").split())
    except ValueError:
        raise typer.BadParameter(f"{value!r} is not a list of layer numbers like 12 or 6,12", param_hint=flag) from None
    if not layers:
        raise typer.BadParameter("give at least one layer, e.g. 12", param_hint=flag)
    return layers


@app.command("slice")
def slice_command(
    run_dir: Path = typer.Option(..., "--run-dir", help="Capture run folder (holds metadata.json)."),
    concept_map_path: Path = typer.Option(..., "--concept-map-path", help="Concept map JSON of the same dataset."),
    output_dir: Path = typer.Option(..., "--output-dir", help="Slices folder, e.g. data/residuals/open_vs_close_slices."),
    token_type: TokenTypeChoice = typer.Option(
        TokenTypeChoice.instructions, "--token-type", help="Token type the run captured."
    ),
    layers: str = typer.Option("12", "--layers", help="Layers to slice, e.g. 12 or 6,12."),
    device: str = typer.Option("cpu", "--device", help="Device for frame means (outputs are saved from CPU)."),
    reduce: ReduceChoice = typer.Option(
        ReduceChoice.token, "--reduce", help="One row per captured token, or their mean per frame."
    ),
    max_samples_per_concept: int | None = typer.Option(
        None, "--max-samples-per-concept", min=1, help="Keep at most N rows (or frames), evenly spaced."
    ),
    verify_checksums: bool = typer.Option(
        False, "--verify-checksums", help="Re-hash every shard against metadata.json before reading it."
    ),
) -> None:
    """Write <output-dir>/layerNN/<concept>.pt (+ .safetensors, index.json) for each concept."""
    with _input_errors():
        settings = SliceSettings(
            layers=_layer_list(layers),
            token_type=token_type.value,
            reduce=reduce.value,
            max_samples_per_concept=max_samples_per_concept,
            verify_checksums=verify_checksums,
            device=device,
        )
        written = slice_concepts(run_dir, concept_map_path, output_dir, settings)
    for layer, index in written.items():
        typer.echo(f"layer {layer}: {index}")
