"""CLI commands that run the Prefect flows: `run`, `demo` and `deploy`.

Prefect is imported inside the commands (after its environment is set), so the library and the
other commands never load it.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

import typer

from cli.app import app, input_errors
from steering_core import demo
from steering_core.config import load_run_config

# Prefect's embedded server needs more than its default 20 s to start on a busy 2-core machine.
EPHEMERAL_STARTUP_SECONDS = "90"


def prefect_environment(home: Path | None = None) -> None:
    """Set Prefect's environment for an in-process run (unless already set): startup, telemetry, logs, offline hub."""
    logging.getLogger("httpx").setLevel(logging.WARNING)  # one line per API call otherwise
    os.environ.setdefault("PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS", EPHEMERAL_STARTUP_SECONDS)
    os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")
    os.environ.setdefault("HF_HUB_OFFLINE", "1")
    os.environ.setdefault("PREFECT_LOGGING_EXTRA_LOGGERS", "steering_core")  # library logs reach the Prefect UI
    if home is not None:
        os.environ.setdefault("PREFECT_HOME", str(home))


@app.command("run")
def run_command(
    config: Path = typer.Option(..., "--config", help="Run config (YAML): sources, pairs, layers, model, SAE."),
) -> None:
    """Run the whole pipeline (the `latent-steering` flow) in this process.

    Uses PREFECT_API_URL when set, else Prefect's embedded server. Re-runs reuse every step whose
    inputs did not change.
    """
    prefect_environment()
    with input_errors():
        run_config = load_run_config(config)
    from flows.pipeline import latent_steering

    result = latent_steering(str(config))
    typer.echo(f"outputs under {result['output_root']}")
    for path in demo.report_paths(run_config):
        typer.echo(f"report: {path}")


@app.command("demo")
def demo_command(
    output_dir: Path = typer.Option(Path("demo_output"), "--output-dir", help="Folder for inputs, outputs and run.yaml."),
    demos_per_task: int = typer.Option(3, "--demos-per-task", min=2, help="Generated demos per task (4 tasks)."),
) -> None:
    """Generate demos for two concept pairs, a tiny pi0.5, tokenizer and SAEs; run the whole flow; summarise.

    Runs offline on Prefect's embedded server (PREFECT_HOME inside the output folder unless set).
    Running it again reuses every cached step.
    """
    output_dir = output_dir.resolve()
    prefect_environment(home=output_dir / ".prefect")
    config_path = demo.build_demo(output_dir, demos_per_task=demos_per_task)
    typer.echo(f"inputs written under {output_dir / demo.INPUTS_DIR}; run config {config_path}")
    from flows.pipeline import latent_steering

    latent_steering(str(config_path))
    run_config = load_run_config(config_path)
    typer.echo("")
    typer.echo(demo.format_summary(demo.summarise(run_config)))
    typer.echo("")
    typer.echo(f"outputs: {run_config.output_root}")
    for path in demo.report_paths(run_config):
        typer.echo(f"report:  {path}")


@app.command("deploy")
def deploy_command(
    config: Path = typer.Option(..., "--config", help="Run config (YAML) the deployments run with."),
    gpu_slots: int = typer.Option(1, "--gpu-slots", min=1, help="GPU tasks allowed at once across all gpu workers."),
) -> None:
    """Create the `gpu` and `cpu` work pools and the `gpu` concurrency limit, then deploy every flow.

    Needs PREFECT_API_URL (a running `prefect server start`); run it from the repository root.
    """
    with input_errors(RuntimeError):
        load_run_config(config)
        from flows.deploy import setup

        setup(config, gpu_slots=gpu_slots)
    typer.echo("deployments: latent-steering/pipeline, latent-steering-capture/gpu, latent-steering-evaluate/gpu-evaluate, "
               "latent-steering-refresh/scheduled")
    typer.echo("start workers: prefect worker start --pool gpu  |  prefect worker start --pool cpu")
