"""`latent-steering serve`: a steered pi0.5 policy server for openpi clients (e.g. openpi's LIBERO example)."""

from __future__ import annotations

from pathlib import Path

import typer

from latent_steering_cli.app import app, input_errors
from latent_steering_cli.numbers import number_option
from latent_steering_cli.options import device_option, model_inputs, model_options
from steering_core.layout import STEERING_ROOT
from steering_core.pi05.spec import ModelSpec
from steering_core.pi05.steering import MAX_ALPHA
from steering_core.serve import (
    PolicyServer,
    SteeredPi05Policy,
    SteeringLimits,
    VectorCatalog,
    parse_steering,
    parse_steering_option,
)
from steering_core.serve.auth import API_KEY_ENV, read_api_key
from steering_core.serve.batching import DEFAULT_BATCH_WAIT_MS, MAX_BATCH, MAX_BATCH_WAIT_MS
from steering_core.serve.episodes import EpisodeLog
from steering_core.serve.server import (
    DEFAULT_IDLE_TIMEOUT_S,
    DEFAULT_INFERENCE_TIMEOUT_S,
    DEFAULT_MAX_BATCH,
    DEFAULT_MAX_CONNECTIONS,
    DEFAULT_MAX_MESSAGE_BYTES,
    DEFAULT_MAX_QUEUE,
    check_address_free,
)
from steering_core.storage.overwrites import check_no_overwrite

DEFAULT_VECTORS = Path("data") / STEERING_ROOT
TOKENIZER_FILES = ("paligemma_tokenizer.model", "tokenizer.json")


@app.command("serve")
@model_options()
def serve_command(
    vectors: Path = typer.Option(
        DEFAULT_VECTORS, "--vectors", help="The steer step's output root (layerNN/<pair>/ folders) to offer clients."
    ),
    steer: list[str] = typer.Option(
        [], "--steer", help="Default steering for requests without a `steering` entry: "
        "pair:layer:alpha[:direction[:alpha_units|mode]], e.g. open_vs_close:12:2.0 (α in residual_norm units, the "
        "evaluation's; :sae:vector for vector units; :sae:clamp to clamp to level fraction α, 0 the negative "
        "concept's mean, 1 the positive's; repeat to combine)."
    ),
    max_alpha: float = number_option(
        MAX_ALPHA, "--max-alpha", min=0.0, help="Refuse steering with |α| above this, in residual_norm units "
        "(α·R is the norm of the shift; the evaluation's grid stays within a few units)."
    ),
    host: str = typer.Option("127.0.0.1", "--host", help="Interface to listen on (0.0.0.0: every interface)."),
    port: int = typer.Option(8000, "--port", min=0, max=65535, help="Port (openpi's default 8000; 0: a free port)."),
    device: str | None = device_option(None),
    dtype: str | None = typer.Option(
        None, "--dtype", help="Compute dtype (default: openpi's bfloat16 policy on CUDA, float32 on CPU)."
    ),
    compiled: bool | None = typer.Option(
        None, "--compiled/--eager", help="Run the denoising step compiled (torch.compile; CUDA graphs on CUDA), paid "
        "once at start-up before /healthz answers (default: compiled on CUDA, eager on CPU)."
    ),
    noise_seed: int | None = typer.Option(
        None, "--noise-seed", help="Use the same initial noise for every request (paired steered/plain comparisons); "
        "default: fresh noise per request, as openpi."
    ),
    max_message_mb: float = number_option(
        DEFAULT_MAX_MESSAGE_BYTES / 2**20, "--max-message-mb", min=0.001, help="Largest observation message accepted "
        "(twice this closes the connection)."
    ),
    inference_timeout_s: float = number_option(
        DEFAULT_INFERENCE_TIMEOUT_S, "--inference-timeout-s", min=0.001, help="Answer a request with an error when "
        "its actions are not ready this many seconds after it arrived (waiting for the model included)."
    ),
    max_connections: int = typer.Option(
        DEFAULT_MAX_CONNECTIONS, "--max-connections", min=1, help="Connections served at once; more are closed "
        "with 1013 (try again later)."
    ),
    max_queue: int = typer.Option(
        DEFAULT_MAX_QUEUE, "--max-queue", min=1, help="Frames a connection may send ahead of the request being "
        "answered before the server stops reading from it."
    ),
    idle_timeout_s: float = number_option(
        DEFAULT_IDLE_TIMEOUT_S, "--idle-timeout-s", min=0.001, help="Close a connection that sends nothing for this "
        "long; at the connection cap, one idle for 30 s gives way to a new client."
    ),
    max_batch: int = typer.Option(
        DEFAULT_MAX_BATCH, "--max-batch", min=1, max=MAX_BATCH, help="Rows per policy call: requests arriving "
        "together (and a request's own leading batch dimension) share one call; 1 serves one request per call."
    ),
    batch_wait_ms: float = number_option(
        DEFAULT_BATCH_WAIT_MS, "--batch-wait-ms", min=0.0, max=MAX_BATCH_WAIT_MS, help="How long the oldest waiting "
        "request waits for others to share its policy call (0: take only those already waiting)."
    ),
    api_key_file: Path | None = typer.Option(
        None, "--api-key-file", help=f"File holding an api key clients must send (Authorization: Api-Key <key>, as "
        f"openpi's client does; others get HTTP 401). Default: ${API_KEY_ENV} if set, else no key."
    ),
    episodes_file: Path | None = typer.Option(
        None, "--episodes-file", help="Append one JSON line per finished episode (openpi's episode_start / "
        "episode_end control messages) to this file."
    ),
    model: ModelSpec | None = None,
) -> None:
    """Serve steered pi0.5 over openpi's websocket protocol until Ctrl-C or SIGTERM.

    Clients add an optional `steering` entry to the observation, e.g. {"pair": "open_vs_close", "layer": 12,
    "alpha": 2.0} (α in residual_norm units by default, as the evaluation's tables; "alpha_units": "vector" for
    α times the method's vector; "direction": a method, e.g. "mean_difference" (default "sae"), or "random_<k>"
    for a norm-matched random control; "mode": "clamp" to set the projection to level fraction α); the server's
    metadata lists the vectors it offers with their R, norm and levels. openpi's episode_start / episode_end
    messages are recorded.
    """
    with input_errors():
        check_no_overwrite({"--episodes-file": episodes_file}, {"--vectors": vectors, "--api-key-file": api_key_file,
                                                                **model_inputs(model)})
        api_key, episode_log = read_api_key(api_key_file), EpisodeLog(episodes_file)
        # the default folder may not exist yet (serve the plain policy); a folder given explicitly must
        catalog = VectorCatalog.scan(vectors) if vectors != DEFAULT_VECTORS or vectors.exists() else VectorCatalog()
        if vectors != DEFAULT_VECTORS and not len(catalog):
            raise ValueError(f"--vectors {vectors}: no steering vectors in it; pass the steer step's output root "
                             f"(holding layerNN/<pair>/ folders)")
        if model is None:
            raise typer.BadParameter("required", param_hint="--checkpoint-path")
        if model.tokenizer is None:
            model = model.model_copy(update={"tokenizer": _tokenizer_beside(model.checkpoint)})
        default = parse_steering([parse_steering_option(text) for text in steer], catalog, key="--steer",
                                 limits=SteeringLimits(max_alpha, model.arch.depth))
        check_address_free(host, port)  # before the model loads
        policy = model.load_policy(device, dtype, compiled)
        policy.normalization.check()  # read now: a missing or broken file stops here, not at a request
        served = SteeredPi05Policy(policy, noise_seed=noise_seed)
        served.check_catalog(catalog)
        server = PolicyServer(served, catalog, default_steering=default, host=host, port=port,
                              max_message_bytes=int(max_message_mb * 2**20), max_alpha=max_alpha, api_key=api_key,
                              episode_log=episode_log, inference_timeout_s=inference_timeout_s,
                              max_connections=max_connections, max_queue=max_queue, max_batch=max_batch,
                              batch_wait_ms=batch_wait_ms, idle_timeout_s=idle_timeout_s)
        server.run()  # an address taken meanwhile: one line too


def _tokenizer_beside(checkpoint_path: Path) -> Path:
    """Return the tokenizer in the checkpoint's folder: PaliGemma's SentencePiece model, else a tokenizer.json."""
    folder = checkpoint_path if checkpoint_path.is_dir() else checkpoint_path.parent
    for name in TOKENIZER_FILES:
        if (folder / name).is_file():
            return folder / name
    raise typer.BadParameter(f"no {' or '.join(TOKENIZER_FILES)} in {folder}; pass the tokenizer",
                             param_hint="--tokenizer-path")
