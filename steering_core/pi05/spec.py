"""`ModelSpec`: the one description of the pi0.5 model a run, a settings class or a command uses: where its files
are (checkpoint, tokenizer, openpi's norm stats), how to read them (layout, arch) and what the checkpoint's folder
may leave open (horizon, prompt format, prompt length, dtype, device).

Unset values come from the checkpoint's folder (`robot_side`): openpi's `config.json` and defaults, or lerobot's
`config.json` and processors. Every consumer asks the spec (`checkpoint`, `robot_side`, `prompt_tokenizer`,
`load_policy`, `load_prefix`), so the same fields cannot be read two ways.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

from pydantic import Field

from steering_core.pi05.arch import ExpertArch, Pi05Arch
from steering_core.pi05.layouts import Checkpoint, LayoutName, resolve_checkpoint
from steering_core.pi05.norm_stats import LIBERO_ASSET_ID
from steering_core.pi05.robot_side import RobotSide, robot_side
from steering_core.pi05.tokenizer import PromptFormat, PromptTokenizer
from steering_core.storage.schema import StrictModel

if TYPE_CHECKING:
    from steering_core.pi05.model import Pi05Prefix
    from steering_core.pi05.policy import Pi05Policy


class ModelSpec(StrictModel):
    """A pi0.5 checkpoint and how it is read and run; None: the checkpoint folder's own value (or the default)."""

    checkpoint: Path = Field(description="pi0.5 checkpoint folder (openpi's converted PyTorch checkpoint or lerobot's "
                             "PI05Policy folder) or its model.safetensors.")
    layout: LayoutName = Field(LayoutName.AUTO, description="The checkpoint's layout: auto (detected from the "
                               "folder), openpi or lerobot (then checked against the folder).")
    tokenizer: Path | None = Field(None, description="PaliGemma tokenizer: its SentencePiece model "
                                   "(paligemma_tokenizer.model) or tokenizer.json (or a folder holding it).")
    norm_stats: Path | None = Field(None, description="openpi's norm_stats.json (default: the checkpoint's "
                                    "assets/<asset-id>/norm_stats.json); lerobot's statistics are its processor files.")
    asset_id: str = Field(LIBERO_ASSET_ID, description="Asset folder of an openpi checkpoint's norm stats.")
    arch: Pi05Arch = Field(Pi05Arch(), description="Language model and SigLIP dimensions (default the real pi0.5).")
    action_horizon: int | None = Field(None, ge=1, le=1000, description="Actions per chunk (default the checkpoint's: "
                                       "openpi action_horizon, lerobot chunk_size; else 10).")
    prompt_format: PromptFormat | None = Field(None, description="libero (pi05_libero: no state) or discrete_state "
                                               "(default: libero for openpi, discrete_state for lerobot).")
    max_token_len: int | None = Field(None, ge=1, le=8192, description="Prompt length in tokens (default lerobot's "
                                      "tokenizer_max_length, else 200).")
    dtype: str | None = Field(None, description="Compute dtype (default: the layout's bfloat16 policy on CUDA, "
                              "float32 on CPU).")
    device: str | None = Field(None, description="Device (default CUDA when available, else CPU).")

    def resolve(self) -> Checkpoint:
        """Return the checkpoint with its layout detected (or forced and checked)."""
        return resolve_checkpoint(self.checkpoint, self.layout)

    def robot_side(self, checkpoint: Checkpoint | None = None) -> RobotSide:
        """Return the statistics, cameras, prompt format, horizon and prompt length the folder and the spec give."""
        return robot_side(checkpoint or self.resolve(), self.arch, self.prompt_format, self.norm_stats, self.asset_id,
                          self.action_horizon, self.max_token_len)

    def require_tokenizer(self) -> Path:
        """Return the tokenizer path; ValueError when the spec names none."""
        if self.tokenizer is None:
            raise ValueError(f"{self.checkpoint}: no tokenizer given; pass PaliGemma's paligemma_tokenizer.model or "
                             "its tokenizer.json (model.tokenizer, --tokenizer-path)")
        return self.tokenizer

    def prompt_tokenizer(self, robot: RobotSide | None = None) -> PromptTokenizer:
        """Return the tokenizer in the checkpoint's prompt format and length."""
        robot = robot or self.robot_side()
        return PromptTokenizer(self.require_tokenizer(), robot.max_token_len, robot.prompt_format)

    def load_policy(self, device: str | None = None, dtype: str | None = None, compiled: bool | None = None,
                    expert_arch: ExpertArch | None = None) -> Pi05Policy:
        """Return the whole policy (`Pi05Policy.from_checkpoint`); `device` and `dtype` override the spec's."""
        from steering_core.pi05.policy import Pi05Policy  # deferred: loads transformers

        return Pi05Policy.from_checkpoint(
            self.checkpoint, self.arch, device=device or self.device, dtype=dtype or self.dtype,
            action_horizon=self.action_horizon, tokenizer_path=self.tokenizer, prompt_format=self.prompt_format,
            norm_stats_path=self.norm_stats, asset_id=self.asset_id, expert_arch=expert_arch, compiled=compiled,
            layout=self.layout, max_token_len=self.max_token_len,
        )

    def load_prefix(self, max_layer: int | None = None, device: str | None = None,
                    dtype: str | None = None) -> Pi05Prefix:
        """Return the prefix model up to `max_layer` (`Pi05Prefix.from_checkpoint`)."""
        from steering_core.pi05.model import Pi05Prefix  # deferred: loads transformers

        return Pi05Prefix.from_checkpoint(self.resolve(), self.arch, max_layer, device or self.device,
                                          dtype or self.dtype)


