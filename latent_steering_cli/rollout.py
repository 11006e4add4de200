"""`latent-steering rollout`: closed-loop steered episodes in the LIBERO simulator (phase 5) from this process, on
its simulation workers, without Prefect."""

from __future__ import annotations

from pathlib import Path

import typer

from latent_steering_cli.app import app, input_errors
from steering_core.config import load_run_config
from steering_core.config.run import run_overwrite_problem
from steering_core.workload import rollout_problems


@app.command("rollout")
def rollout_command(
    config: Path = typer.Option(..., "--config", help="Run config (YAML) with a `rollout` section; phases 1-3 done."),
    pair: list[str] = typer.Option([], "--pair", help="Roll out only this pair (repeat; default: every mapped pair)."),
    layer: list[int] = typer.Option([], "--layer", help="Roll out only this layer (repeat; default: every layer)."),
    policy: str | None = typer.Option(
        None, "--policy", help="\"local\" (in-process) or ws://host:port of a `latent-steering serve` (default: the "
        "config's rollout.policy)."
    ),
    api_key_file: Path | None = typer.Option(None, "--api-key-file", help="File holding the server's API key."),
    libero_assets: str | None = typer.Option(
        None, "--libero-assets", help="LIBERO scene assets: \"installed\" (the PyPI packages, verified against "
        "upstream hashes), a folder (verified), or \"download\" (hf-libero fetches them from the hub)."
    ),
    episodes: int | None = typer.Option(None, "--episodes", min=1, help="Episodes per cell (default: the config's)."),
    workers: int | None = typer.Option(
        None, "--workers", help="Chunks simulated at once in worker processes, 1 to 256 (default: the config's "
        "rollout.workers, else one per usable core within the memory)."
    ),
) -> None:
    """Run the steered policy in the LIBERO simulator per pair, layer, α and control; write rollouts/layerNN/.

    Each cell's rollouts.json and .safetensors, success-vs-α plots with Wilson intervals and the random band,
    joint trajectories, an MP4 of each cell's first episode, and a summary.md per layer.
    """
    from steering_core.preflight import rollout_input_problems
    from steering_core.rollout.local_run import rollout_config
    from steering_core.serve.auth import read_api_key

    with input_errors():
        run_config = load_run_config(config)
        if run_config.rollout is None:
            raise ValueError(f"{config}: no `rollout` section; map each pair to its LIBERO tasks there")
        overrides = {key: value for key, value in (("policy", policy), ("api_key_file", api_key_file),
                                                   ("libero_assets", libero_assets), ("episodes", episodes),
                                                   ("workers", workers))
                     if value is not None}
        section = run_config.rollout.model_validate({**run_config.rollout.model_dump(), **overrides})
        run_config = run_config.model_copy(update={"rollout": section})
        if (problem := run_overwrite_problem(run_config)) is not None:  # --api-key-file inside the outputs
            raise ValueError(problem)
        targets = [(name, at) for name, at in run_config.rollout_targets()
                   if (not pair or name in pair) and (not layer or at in layer)]
        if not targets:
            chosen = " ".join([*(f"--pair {name}" for name in pair), *(f"--layer {at}" for at in layer)])
            raise ValueError(f"{chosen}: no (pair, layer) left to roll out: the config maps {sorted(section.pairs)} "
                             f"at layers {list(run_config.layers)}")
        if problems := rollout_input_problems(run_config) + rollout_problems(run_config, targets,
                                                                             where=f"{config}: rollout"):
            raise ValueError("; ".join(problems))
        summaries = rollout_config(run_config, targets, api_key=read_api_key(section.api_key_file))
    for layer_number, path in summaries.items():
        typer.echo(f"layer {layer_number}: {path}")
