"""How an SAE is trained on π0.5's residual rows: architecture, sizes, optimiser, stream and checkpoints."""

from __future__ import annotations

from typing import Literal

from pydantic import Field, model_validator

from steering_core.storage.schema import StrictModel

Architecture = Literal["topk", "batchtopk", "jumprelu", "standard"]
ARCHITECTURES: tuple[str, ...] = Architecture.__args__
Normalization = Literal["none", "expected_average_only_in"]
SPARSE_BY_K = ("topk", "batchtopk")  # sparsity set by k; the others by a loss coefficient


class TrainSettings(StrictModel):
    """One SAE training run; real sizes by default (Gemma-2B width rows, 16384 latents as the borrowed SAE)."""

    architecture: Architecture = "topk"
    d_sae: int = Field(16384, ge=1)
    k: int = Field(64, ge=1)  # topk: latents kept per row; batchtopk: per row on average over a batch
    # jumprelu: l0 coefficient; standard: l1 coefficient (SAELens's defaults are 1.0 for both)
    sparsity_coefficient: float = Field(1.0, gt=0)
    lr: float = Field(3e-4, gt=0, le=1)
    batch_size: int = Field(4096, ge=1)  # rows per optimiser step
    training_rows: int = Field(2_000_000, ge=1)  # rows seen in all; the run's rows repeat in new orders if fewer
    # SAELens's: inputs scaled to mean norm sqrt(d_in) during training, the factor folded into the saved weights
    normalize: Normalization = "expected_average_only_in"
    norm_estimate_batches: int = Field(16, ge=1)  # batches of a separate stream that estimate that factor
    # rows shuffled together: 262144 x 2048 float32 rows are 2 GiB, a bound whatever the run's size
    buffer_rows: int = Field(262_144, ge=1)
    seed: int = Field(0, ge=0, lt=2**31)  # initial weights and row order
    checkpoints: int = Field(4, ge=0)  # evenly spaced during training; a rerun after a kill resumes from the last
    dead_feature_window: int = Field(1000, ge=1)  # steps without firing before a latent counts as dead
    feature_sampling_window: int = Field(2000, ge=1)  # steps over which firing frequency is counted
    device: str = "auto"  # steering_core.devices.resolve_device

    @model_validator(mode="after")
    def _check_sizes(self) -> TrainSettings:
        """Refuse combinations no SAE can train with, each named."""
        problems = []
        if self.architecture in SPARSE_BY_K and self.k > self.d_sae:
            problems.append(f"k is {self.k}, expected at most d_sae ({self.d_sae})")
        if self.batch_size > self.training_rows:
            problems.append(f"batch_size is {self.batch_size}, expected at most training_rows ({self.training_rows})")
        if problems:
            raise ValueError("; ".join(problems))
        return self

