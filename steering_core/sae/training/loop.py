"""SAELens's side of training: the training SAE of an architecture, its SAETrainer, and their state for checkpoints.

This module imports SAELens (about 15 s of CPU: it pulls in transformer_lens, wandb and transformers), so
`trainer` imports it only when a training really starts; `rows` and `settings` stay light.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from typing import Any

import torch
from sae_lens import SAETrainer
from sae_lens.config import SAETrainerConfig
from sae_lens.saes.batchtopk_sae import BatchTopKTrainingSAE, BatchTopKTrainingSAEConfig
from sae_lens.saes.jumprelu_sae import JumpReLUTrainingSAE, JumpReLUTrainingSAEConfig
from sae_lens.saes.sae import SAEMetadata, TrainingSAE
from sae_lens.saes.standard_sae import StandardTrainingSAE, StandardTrainingSAEConfig
from sae_lens.saes.topk_sae import TopKTrainingSAE, TopKTrainingSAEConfig

from steering_core.sae.formats import HOOK_NAME
from steering_core.sae.training.settings import TrainSettings

# architecture -> (training SAE, its config, the config field our `sparsity_coefficient` sets, if any)
_TRAINING_CLASSES: dict[str, tuple[type[TrainingSAE], type, str | None]] = {
    "topk": (TopKTrainingSAE, TopKTrainingSAEConfig, None),
    "batchtopk": (BatchTopKTrainingSAE, BatchTopKTrainingSAEConfig, None),
    "jumprelu": (JumpReLUTrainingSAE, JumpReLUTrainingSAEConfig, "l0_coefficient"),
    "standard": (StandardTrainingSAE, StandardTrainingSAEConfig, "l1_coefficient"),
}
# trainer attributes a checkpoint restores, besides the optimiser and the schedulers
_COUNTERS = ("n_training_samples", "n_training_steps", "n_frac_active_samples", "started_fine_tuning")
_STATISTICS = ("act_freq_scores", "n_forward_passes_since_fired")  # (d_sae,) firing counts


def build_sae(settings: TrainSettings, d_in: int, *, layer: int, model_name: str) -> TrainingSAE:
    """Return a freshly initialised SAELens training SAE (float32, CPU), its weights drawn from `settings.seed`.

    The metadata names π0.5's hook as `blocks.<layer>.hook_resid_post`, as SAELens's own SAEs name theirs.
    """
    sae_class, config_class, coefficient = _TRAINING_CLASSES[settings.architecture]
    options: dict[str, Any] = {"k": settings.k} if coefficient is None else {coefficient: settings.sparsity_coefficient}
    config = config_class(
        d_in=d_in, d_sae=settings.d_sae, normalize_activations=settings.normalize, **options,
        metadata=SAEMetadata(hook_name=HOOK_NAME.format(layer=layer), hook_layer=layer, model_name=model_name),
    )
    with torch.random.fork_rng(devices=[]):  # the caller's random state stays as it was
        torch.manual_seed(settings.seed)
        return sae_class(config)


class CheckpointingTrainer(SAETrainer):
    """SAELens's SAETrainer, plus: the last step's losses, a per-step callback, and its state as plain tensors.

    SAELens decides when to checkpoint (`n_checkpoints` evenly spaced thresholds) and calls `on_checkpoint`;
    its own checkpoint files are never written (no `checkpoint_path`): ours are written atomically and read back
    with weights_only loading.
    """

    def __init__(self, settings: TrainSettings, sae: TrainingSAE, device: torch.device, *,
                 on_step: Callable[[int], None], on_checkpoint: Callable[[], None]) -> None:
        config = SAETrainerConfig(
            total_training_samples=settings.training_rows, train_batch_size_samples=settings.batch_size,
            lr=settings.lr, lr_end=settings.lr,  # constant schedule; SAELens leaves lr_end unset otherwise
            device=str(device), dead_feature_window=settings.dead_feature_window,
            feature_sampling_window=settings.feature_sampling_window, n_checkpoints=settings.checkpoints,
            n_batches_for_norm_estimate=settings.norm_estimate_batches,
        )
        # on the device before the optimiser exists: optimiser state loaded from a checkpoint follows the parameters
        super().__init__(config, sae.to(device), data_provider=iter(()),
                         save_checkpoint_fn=lambda checkpoint_path: on_checkpoint())
        self.on_step = on_step
        self.last_losses: dict[str, float] = {}
        self.last_explained_variance = float("nan")

    def step(self, batch: torch.Tensor) -> Any:
        """Run SAELens's training step on one (batch, d_in) batch; remember its losses, then call `on_step`."""
        output = super().step(batch)
        with torch.no_grad():
            self.last_losses = {"loss": float(output.loss), **{k: float(v) for k, v in output.losses.items()}}
            error = (output.sae_out - output.sae_in).pow(2).sum()
            spread = (output.sae_in - output.sae_in.mean(0)).pow(2).sum()
            self.last_explained_variance = float(1 - error / spread)
        self.on_step(self.n_training_samples)
        return output

    def start(self, data: Iterator[torch.Tensor], scaling_data: Iterator[torch.Tensor] | None) -> None:
        """Set the training stream and, on a fresh start with SAELens's normalisation, estimate its factor.

        The estimate reads `scaling_data` (SAELens reads its training stream for it, which would shift where
        training starts in a resumed stream). Checkpoint thresholds already passed are dropped.
        """
        self.data_provider = data
        if scaling_data is not None and self.activation_scaler.scaling_factor is None:
            self.activation_scaler.estimate_scaling_factor(
                self.sae.cfg.d_in, scaling_data, self.cfg.n_batches_for_norm_estimate)
        self.checkpoint_thresholds = [t for t in self.checkpoint_thresholds if t >= self.n_training_samples]

    def state(self) -> dict[str, Any]:
        """Return what a resume needs beyond the SAE's weights: tensors and plain containers only (weights_only)."""
        return {
            "optimizer": self.optimizer.state_dict(),
            "lr_scheduler": self.lr_scheduler.state_dict(),
            "coefficient_schedulers": {name: s.state_dict() for name, s in self.coefficient_schedulers.items()},
            "scaling_factor": self.activation_scaler.scaling_factor,
            **{name: getattr(self, name) for name in _COUNTERS},
            **{name: getattr(self, name).detach().cpu() for name in _STATISTICS},
            # SAELens checkpoints after a step but before counting it: the resumed run starts at the next step
            "n_training_steps": self.n_training_steps + 1,
        }

    def load_state(self, state: dict[str, Any]) -> None:
        """Restore `state()` of a checkpoint."""
        self.optimizer.load_state_dict(state["optimizer"])
        self.lr_scheduler.load_state_dict(state["lr_scheduler"])
        for name, scheduler_state in state["coefficient_schedulers"].items():
            self.coefficient_schedulers[name].load_state_dict(scheduler_state)
        self.activation_scaler.scaling_factor = state["scaling_factor"]
        for name in _COUNTERS:
            setattr(self, name, state[name])
        for name in _STATISTICS:
            setattr(self, name, state[name].to(self.cfg.device))


def inference_files(sae: TrainingSAE, trainer: SAETrainer) -> tuple[dict[str, torch.Tensor], dict[str, Any],
                                                                   dict[str, torch.Tensor]]:
    """Return the trained SAE as SAELens saves it for inference: (weights, cfg.json content, sparsity tensors).

    What SAELens's `save_inference_model` writes, computed on copies (its TopK saving folds decoder norms into
    the tensors it is given) so that our writers can make the files atomic and byte-reproducible.
    """
    weights = {name: tensor.detach().cpu().clone() for name, tensor in sae.state_dict().items()}
    sae.process_state_dict_for_saving_inference(weights)
    weights = {name: tensor.contiguous() for name, tensor in weights.items()}
    return weights, sae.cfg.get_inference_sae_cfg_dict(), {"sparsity": trainer.log_feature_sparsity.contiguous()}
