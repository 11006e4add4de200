"""`latent-steering`: one subcommand per step of the seed pipeline."""

from steering_core.cli import capture, contrast, prepare, run, steer  # noqa: F401  (register commands)
from steering_core.cli.app import app

__all__ = ["app"]
