"""Tiny LIBERO builders shared by the LIBERO, filtering and conversion tests."""

from __future__ import annotations

import hashlib
from collections.abc import Callable
from pathlib import Path

import h5py

from steering_core.synthetic.libero import (
    MotionSpec,
    SyntheticFile,
    SyntheticSettings,
    SyntheticTask,
    write_libero_file,
)

TINY = SyntheticSettings(image_size=16, num_steps=8, state_dim=12)


def tiny_task(instruction: str, scene: str = "KITCHEN_SCENE1", axis: int = 2, direction: int = 1) -> SyntheticTask:
    """Return a synthetic task with default motion."""
    return SyntheticTask(instruction=instruction, scene=scene, motion=MotionSpec(axis=axis, direction=direction))


def write_tiny(
    folder: Path,
    instruction: str,
    scene: str = "KITCHEN_SCENE1",
    *,
    num_demos: int = 1,
    settings: SyntheticSettings = TINY,
    **kwargs,
) -> SyntheticFile:
    """Write a tiny LIBERO file (16 px, 8 steps) and return it."""
    folder.mkdir(parents=True, exist_ok=True)
    return write_libero_file(folder, tiny_task(instruction, scene), num_demos=num_demos, settings=settings, **kwargs)


def edit_file(path: Path, change: Callable[[h5py.File], None]) -> None:
    """Apply `change` to an hdf5 file opened read-write (to corrupt or strip it)."""
    with h5py.File(path, "r+") as handle:
        change(handle)


def sha256_bytes(path: Path) -> str:
    """Return the sha256 of the file's bytes, computed in one read (independent of fileio)."""
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()
