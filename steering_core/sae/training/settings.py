"""How an SAE is trained on π0.5's residual rows: architecture, sizes, optimiser, stream and checkpoints."""

from __future__ import annotations

from typing import Literal

from pydantic import Field, model_validator

from steering_core.devices import DEVICE_HELP
from steering_core.storage.schema import StrictModel

Architecture = Literal["topk", "batchtopk", "jumprelu", "standard"]
ARCHITECTURES: tuple[str, ...] = Architecture.__args__
Normalization = Literal["none", "expected_average_only_in"]
SPARSE_BY_K = ("topk", "batchtopk")  # sparsity set by k; the others by a loss coefficient


class TrainSettings(StrictModel):
    """One SAE training run; real sizes by default (Gemma-2B width rows, 16384 latents as the borrowed SAE)."""

    architecture: Architecture = Field("topk", description="SAELens architecture.")
    d_sae: int = Field(16384, ge=1, le=2**20, description="Latent count (at most 2^20, the widest public SAEs).")
    k: int = Field(64, ge=1, le=4096, description="Active latents per row (topk; batchtopk: per row on average over a batch).")
    sparsity_coefficient: float = Field(  # SAELens's defaults are 1.0 for both
        1.0, gt=0, description="L0 (jumprelu) or L1 (standard) loss coefficient.")
    lr: float = Field(3e-4, gt=0, le=1, description="Adam learning rate.")
    batch_size: int = Field(4096, ge=1, le=2**16, description="Rows per training step.")
    training_rows: int = Field(2_000_000, ge=1, le=10**10,
                               description="Rows seen in all (the run's rows repeat in new orders when fewer).")
    # SAELens's: inputs scaled to mean norm sqrt(d_in) during training, the factor folded into the saved weights
    normalize: Normalization = Field("expected_average_only_in",
                                     description="Input normalisation, folded into the weights at the end.")
    norm_estimate_batches: int = Field(16, ge=1, le=10_000, description="Batches that estimate the normalisation factor.")
    # 262144 x 2048 float32 rows are 2 GiB; the bound, 2^21 rows, 16 GiB
    buffer_rows: int = Field(262_144, ge=1, le=2**21,
                             description="Rows held in the shuffle buffer (bounds memory whatever the run's size).")
    seed: int = Field(0, ge=0, lt=2**31, description="Initialisation and shuffling seed.")
    checkpoints: int = Field(4, ge=0, le=1000, description="Checkpoints during training; a rerun resumes from the latest.")
    dead_feature_window: int = Field(1000, ge=1, le=10**7, description="Steps without firing before a latent counts as dead.")
    feature_sampling_window: int = Field(2000, ge=1, le=10**7, description="Steps over which firing frequency is counted.")
    device: str = Field("auto", description=DEVICE_HELP)  # devices.resolve_device

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

