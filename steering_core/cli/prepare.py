"""CLI commands of one pipeline phase."""

from steering_core.cli.app import app  # noqa: F401
