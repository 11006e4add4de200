"""`latent-steering`: one subcommand per step of the seed pipeline."""

from cli import capture, contrast, evaluate, prepare, run, serve, steer  # noqa: F401  (register commands)
from cli.app import app

__all__ = ["app"]
