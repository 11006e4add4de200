"""The run config of a run, parsed once per process: its flows and tasks read the one the run started with.

The CLI (or the parent flow) parses and checks the config, then shares it (`sharing`); a flow or task of the same
run in the same process gets that parse from `run_config`, and only one started in a process of its own (a worker's
deployment run) reads the file again.
"""

from __future__ import annotations

import contextlib
import contextvars
import os
from collections.abc import Iterator
from pathlib import Path

from steering_core.config import RunConfig, load_run_config
from steering_core.storage.mirrors import is_url

_SHARED: contextvars.ContextVar[dict[str, RunConfig] | None] = contextvars.ContextVar("run_configs", default=None)


def _key(config_path: str | os.PathLike) -> str:
    return str(config_path) if is_url(config_path) else str(Path(config_path).resolve())


@contextlib.contextmanager
def sharing(config: RunConfig, *config_paths: str | os.PathLike) -> Iterator[None]:
    """Within the block, `run_config` of any of `config_paths` returns `config` (in this thread and those it starts)."""
    token = _SHARED.set((_SHARED.get() or {}) | {_key(path): config for path in config_paths})
    try:
        yield
    finally:
        _SHARED.reset(token)


def run_config(config_path: str | os.PathLike) -> RunConfig:
    """Return the run config at `config_path`: the run's shared one (`sharing`), else read from the file now."""
    shared = (_SHARED.get() or {}).get(_key(config_path))
    return shared if shared is not None else load_run_config(config_path)
