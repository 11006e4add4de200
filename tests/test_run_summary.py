"""The closing table of a pipeline run: one row per task run, states as ran/cached/failed, outputs under the root."""

from __future__ import annotations

import base64
import json
import socket
from pathlib import Path

from latent_steering_cli.summary import TaskRow, _pair, format_task_rows, step_names
from tasks.artifacts import ui_report


def test_pair_and_side_come_from_the_run_name():
    pairs = ["open_vs_close", "on_vs_off"]
    assert _pair("encode on_vs_off negative layer 2", pairs) == "on_vs_off negative"
    assert _pair("slice open_vs_close layer 1", pairs) == "open_vs_close"
    assert _pair("capture episodes 8-11", pairs) == "episodes 8-11"
    assert _pair("pairwise stats layer 1", pairs) == "-"


def test_every_pipeline_task_has_a_step_name():
    names = set(step_names().values())
    assert {"preflight", "filter-demos", "convert-dataset", "capture-residuals", "slice-concepts", "encode-concept",
            "pair-directions", "write-report"} <= names


def test_table_shows_states_attempts_times_and_relative_outputs():
    root = Path("/data/out")
    rows = [
        TaskRow("slice-concepts", "open_vs_close", "1", "ran", 0.42, 2, "/data/out/residuals/open_vs_close_slices/layer01/"),
        TaskRow("encode-concept", "on_vs_off negative", "2", "cached", 0.0, 1, "/data/out/latent_steering/x.json"),
        TaskRow("capture-residuals", "episodes 0-7", "-", "failed", 11.04, 3, "-"),
        TaskRow("write-run-metadata", "-", "-", "ran", 0.01, 1, "/elsewhere/metadata.json"),
    ]
    assert format_task_rows(rows, root).splitlines() == [
        "step                pair                layer  state                time    output (under /data/out)",
        "slice-concepts      open_vs_close       1      ran (2 attempts)     0.4 s   residuals/open_vs_close_slices/layer01/",
        "encode-concept      on_vs_off negative  2      cached               0.0 s   latent_steering/x.json",
        "capture-residuals   episodes 0-7        -      failed (3 attempts)  11.0 s  -",
        "write-run-metadata  -                   -      ran                  0.0 s   /elsewhere/metadata.json",
        "4 task runs: 2 ran, 1 cached, 1 failed",
    ]


def test_ui_report_inlines_every_plot_and_says_where_the_files_are(tmp_path):
    png = b"\x89PNG\r\n\x1a\n fake image bytes"
    (tmp_path / "pairwise_cosine.png").write_bytes(png)
    (tmp_path / "summary.md").write_text("# Steering vectors, layer01\n\n![pairwise cosines](pairwise_cosine.png)\n")
    summary = {"plots": {"pairwise_cosine": "pairwise_cosine.png"}}
    (tmp_path / "summary.json").write_text(json.dumps(summary))
    text = ui_report(tmp_path, summary)
    assert f"![pairwise cosines](data:image/png;base64,{base64.b64encode(png).decode()})" in text
    assert "](pairwise_cosine.png)" not in text and "file://" not in text
    assert f"On `{socket.gethostname()}`, in `{tmp_path}`:" in text and "- `pairwise_cosine.png`" in text
