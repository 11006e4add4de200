"""`latent-steering`: one subcommand per step of the seed pipeline.

Command modules are imported only when their command runs (`cli.lazy`), so `--help` and the light
commands start without torch, lerobot or Prefect.
"""

from cli.app import app

__all__ = ["app"]
