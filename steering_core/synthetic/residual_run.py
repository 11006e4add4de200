"""Capture runs made of given residual rows, for the SAE training tests and benchmark."""

from __future__ import annotations

from pathlib import Path

import torch

from steering_core.capture import shards

LAYER = 3  # any captured layer: the rows are given, not computed
TOKENS_PER_FRAME = 2  # rows of one frame share `index`; their token positions are 5 and 6


def write_rows_run(run_dir: Path, rows: torch.Tensor, *, episodes: int = 4, layer: int = LAYER,
                   episodes_per_shard: int = 1, storage_dtype: str = "float32") -> Path:
    """Write `rows` (n, width) as a finished capture run of one layer, split evenly into `episodes`, in order.

    Row i has `index` i // TOKENS_PER_FRAME and `token_id` i, so shard order is the order of `rows`.
    """
    n, width = rows.shape
    spec = shards.RunSpec(token_type="instructions", layers=(layer,), width=width, storage_dtype=storage_dtype,
                          episodes_per_shard=episodes_per_shard, inputs={"checkpoint": "planted"})
    shards.write_run_spec(run_dir, spec)
    bounds = [round(e * n / episodes / TOKENS_PER_FRAME) * TOKENS_PER_FRAME for e in range(episodes + 1)]
    bounds[-1] = n
    for key, members in shards.group_episodes(range(episodes), episodes_per_shard).items():
        start, stop = bounds[members[0]], bounds[members[-1] + 1]  # the members' rows are consecutive
        number = torch.arange(start, stop)
        episode = torch.cat([torch.full((bounds[e + 1] - bounds[e],), e) for e in members])
        first = torch.tensor([bounds[e] // TOKENS_PER_FRAME for e in members])[episode - members[0]]
        shard = shards.ShardRows(residuals=rows[start:stop], index=number // TOKENS_PER_FRAME, episode_index=episode,
                                 frame_index=number // TOKENS_PER_FRAME - first,
                                 token_position=5 + number % TOKENS_PER_FRAME, token_id=number)
        shards.write_shard(run_dir, spec, layer, key, shard, episodes=members, inputs="planted")
    shards.write_run_metadata(run_dir)
    return run_dir
