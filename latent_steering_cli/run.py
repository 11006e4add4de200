"""CLI commands that run the Prefect flows: `run`, `demo` and `deploy`.

Prefect is imported inside the commands (after its environment is set), so the library and the
other commands never load it. One rule for Prefect's state (its database and run history), for `run`
and `demo` alike: `.prefect/` beside the run config, unless PREFECT_HOME is set.
"""

from __future__ import annotations

import functools
import os
import signal
import subprocess
import types
import unittest.mock
from pathlib import Path

import typer

from latent_steering_cli.app import app, input_errors
from latent_steering_cli.numbers import number_option
from steering_core import demo
from steering_core.config import RunConfig, load_run_config
from steering_core.preflight import check_run
from steering_core.processes import die_with_parent
from steering_core.storage.os_limits import check_writable_folder

# Prefect's embedded server needs more than its default 20 s to start on a busy 2-core machine.
EPHEMERAL_STARTUP_SECONDS = "90"
PREFECT_HOME_DIR = ".prefect"  # beside the run config, unless PREFECT_HOME is set


def prefect_environment(home: Path | None = None) -> None:
    """Set Prefect's environment for an in-process run (unless already set): startup, telemetry, logs, offline hub."""
    os.environ.setdefault("PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS", EPHEMERAL_STARTUP_SECONDS)
    os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")
    os.environ.setdefault("HF_HUB_OFFLINE", "1")
    os.environ.setdefault("PREFECT_LOGGING_EXTRA_LOGGERS", "steering_core")  # library logs reach the Prefect UI
    # its INFO lines outside a flow run (demo inputs, preflight) go to the console only, without Prefect's warning
    os.environ.setdefault("PREFECT_LOGGING_TO_API_WHEN_MISSING_FLOW", "ignore")
    if home is not None:
        os.environ.setdefault("PREFECT_HOME", str(home))
    check_prefect_home()


def check_prefect_home() -> Path:
    """Return Prefect's home folder ($PREFECT_HOME, else ~/.prefect) once a file can be written there; ValueError
    naming the variable and the folder otherwise (before Prefect starts: it keeps its database there)."""
    home = Path(os.environ.get("PREFECT_HOME", "~/.prefect")).expanduser()
    return check_writable_folder(home, "PREFECT_HOME", "Prefect keeps its database and settings there: set "
                                 "PREFECT_HOME to a writable folder (or unset it to use .prefect/ beside the run config)")


def run_pipeline(config_path: Path, run_config: RunConfig) -> None:
    """Run the `latent-steering` flow in this process; print what each task did; exit 1 if the run failed."""
    from flows.pipeline import latent_steering
    from latent_steering_cli.summary import format_task_rows, task_rows, task_runs_of
    from tasks.run_configs import sharing

    start_embedded_server()
    with sharing(run_config, config_path):  # the flow reads this parse, not the file again
        state = latent_steering(str(config_path), return_state=True)
    typer.echo("")
    typer.echo(format_task_rows(task_rows(task_runs_of(state.state_details.flow_run_id), run_config),
                                run_config.output_root))
    if not state.is_completed():
        typer.secho(f"error: the run ended {state.name}: {state.message}", fg=typer.colors.RED, err=True)
        raise typer.Exit(1)


def start_embedded_server() -> None:
    """Start Prefect's embedded server now, unless PREFECT_API_URL names a server: in a session of its own, so a
    terminal's Ctrl-C (sent to its process group) stops only this process, which records its runs Crashed there
    before stopping the server (at exit, Prefect's own stop); the server dies with this process too (kill -9).

    Prefect starts it on first use, as a child in this process group (`SubprocessASGIServer`, one per process):
    started here with the same command, only detached."""
    import prefect.server.api.server as embedded
    from prefect.client.orchestration import get_client
    from prefect.settings import PREFECT_API_URL

    if PREFECT_API_URL.value():
        return
    detached = types.SimpleNamespace(**{**vars(subprocess), "Popen": functools.partial(
        subprocess.Popen, start_new_session=True, preexec_fn=functools.partial(die_with_parent, signal.SIGTERM))})
    with unittest.mock.patch.object(embedded, "subprocess", detached):
        get_client(sync_client=True)  # starts the server (`get_client` does without PREFECT_API_URL)


@app.command("run")
def run_command(
    config: Path = typer.Option(..., "--config", help="Run config (YAML): sources, pairs, layers, model, SAE."),
) -> None:
    """Run the whole pipeline (the `latent-steering` flow) in this process.

    Uses PREFECT_API_URL when set (checked to answer first), else Prefect's embedded server.
    Prefect's state (database, run history) is kept in .prefect/ beside the run config, unless PREFECT_HOME is set.
    Re-runs reuse every step whose inputs did not change.
    Ends with a table of every task run: ran, cached or failed, time, output.
    """
    with input_errors():
        run_config = load_run_config(config)
        prefect_environment(home=config.resolve().parent / PREFECT_HOME_DIR)
        if os.environ.get("PREFECT_API_URL"):  # a server of one's own: it must answer before the run starts
            from deployments.setup import check_api_answers

            check_api_answers(os.environ["PREFECT_API_URL"])
        check_run(run_config, capture_device=run_config.orchestration.mode != "deployment")  # before Prefect starts
    run_pipeline(config, run_config)
    _echo_outcome(run_config, random_sae=False)


@app.command("demo")
def demo_command(
    output_dir: Path = typer.Option(Path("demo_output"), "--output-dir", help="Folder for inputs, outputs and run.yaml."),
    demos_per_task: int = typer.Option(3, "--demos-per-task", min=2, help="Generated demos per task (4 tasks)."),
) -> None:
    """Generate demos for two concept pairs, a tiny pi0.5, tokenizer and SAEs; run the whole flow; summarise.

    First a one-pair run whose concept is planted in its model checks that the evaluation finds it.

    Runs offline on Prefect's embedded server.
    Prefect's state is kept in <output-dir>/.prefect (beside the run config, as for `run`), unless PREFECT_HOME is set.
    Running it again reuses every cached step.
    """
    output_dir = output_dir.resolve()
    with input_errors():
        demo.check_demo_request(output_dir, demos_per_task)
        prefect_environment(home=output_dir / PREFECT_HOME_DIR)
    planted_path = demo.build_planted(output_dir / demo.PLANTED_DIR)
    config_path = demo.build_demo(output_dir, demos_per_task=demos_per_task)
    typer.echo(f"inputs written under {output_dir / demo.INPUTS_DIR}; run config {config_path}")
    typer.echo(f"first, the planted-concept check: run config {planted_path}")
    planted = load_run_config(planted_path)
    run_pipeline(planted_path, planted)
    run_config = load_run_config(config_path)
    run_pipeline(config_path, run_config)
    _echo_outcome(run_config, random_sae=True)
    typer.echo("")
    typer.echo("The planted-concept check (a concept that truly exists in its model; the right answer is the mean "
               "difference at α = 1, efficacy 1 on both sides):")
    typer.echo(demo.format_evaluation(demo.evaluation_answer(planted)))
    typer.echo("")
    typer.echo(demo.format_rollouts(run_config))


def _echo_outcome(run_config: RunConfig, random_sae: bool) -> None:
    """Print the steering-vector summary, the output root and the report paths of a finished run."""
    typer.echo("")
    typer.echo(demo.format_summary(demo.summarise(run_config), random_sae=random_sae))
    typer.echo("")
    typer.echo(f"outputs: {run_config.output_root}")
    for path in demo.report_paths(run_config):
        typer.echo(f"report: {path}")


@app.command("deploy")
def deploy_command(
    config: str = typer.Option(..., "--config", help="Run config (YAML) the deployments run with: a path, or its URL "
                                                     "(s3://...) for workers on other machines."),
    gpu_slots: int = typer.Option(1, "--gpu-slots", min=1, help="GPU tasks allowed at once across all gpu workers."),
    storage: str | None = typer.Option(
        None, "--storage", help="Bucket URL (s3://bucket/prefix, gs://...) for Prefect's results: checked writable, "
                                "saved as the block `latent-steering-results`, named in the deployments' env."),
    heartbeat_timeout: float | None = number_option(
        None, "--heartbeat-timeout", help="Seconds of heartbeat silence after which the deploy automation marks a "
                                          "flow run Crashed, the last resort for runs no parent watches (default 600; "
                                          "deployments/README.md)."),
) -> None:
    """Create the `gpu` and `cpu` work pools and the `gpu` concurrency limit, then deploy every flow.

    Needs PREFECT_API_URL (a running `prefect server start`); run it from the repository root. With --storage, the
    bucket is checked writable first and Prefect's results go there (deployments/README.md, "A fleet").
    """
    with input_errors(RuntimeError):
        load_run_config(config)
        check_prefect_home()
        from deployments.setup import RESULTS_BLOCK, setup

        timeout = {} if heartbeat_timeout is None else {"heartbeat_timeout": heartbeat_timeout}
        results = setup(config, gpu_slots=gpu_slots, storage=storage, **timeout)
    typer.echo("deployments: latent-steering/pipeline, latent-steering-capture/gpu, latent-steering-evaluate/gpu-evaluate, "
               "latent-steering-train-sae/gpu-train-sae, latent-steering-rollout/sim-rollout, latent-steering-refresh/scheduled")
    if results is not None:
        typer.echo(f"result storage: block {RESULTS_BLOCK} -> {results}")
    typer.echo("start workers: prefect worker start --pool gpu  |  prefect worker start --pool cpu")
