"""`latent-steering`: one subcommand per step of the seed pipeline.

Command modules are imported only when their command runs (`latent_steering_cli.lazy`), so `--help` and the light
commands start without torch, lerobot or Prefect.
"""

from latent_steering_cli.app import app

__all__ = ["app"]
