"""Rollout plots: both PNGs draw from a synthetic pair's cells; ended episodes hold their last joint value."""

from __future__ import annotations

import numpy as np
from helpers_rollout import DRAWER_GOALS, PAIR, write_pair_cells

from steering_core.rollout.plots import held_after_end, plot_joints, plot_success
from steering_core.rollout.records import read_cell


def test_success_and_joint_plots_are_written(tmp_path):
    write_pair_cells(tmp_path, n=3, frames=0)
    cells = [read_cell(p.parent) for p in sorted((tmp_path / PAIR).glob("*/rollouts.json"))]
    plot_success(tmp_path / "success.png", [record for record, _ in cells])
    plot_joints(tmp_path / "joints.png", cells, DRAWER_GOALS)
    for name in ("success.png", "joints.png"):
        assert (tmp_path / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_ended_episodes_hold_their_last_value():
    values = np.array([[0.0, -0.1, np.nan, np.nan], [0.0, 0.1, 0.2, 0.3]])
    held = held_after_end(values, np.array([1, 3]))
    assert held.tolist() == [[0.0, -0.1, -0.1, -0.1], [0.0, 0.1, 0.2, 0.3]] and np.isnan(values[0, 2])
