"""Training SAEs on captured residual rows with SAELens.

Modules: `rows` (RowSource: one layer's rows, in shard order or shuffled), `settings` (TrainSettings), `trainer`
(train_sae: SAELens's folder, checkpoints, resume), `loop` (SAELens's trainer and training SAEs; imported only when a
training starts, as SAELens takes ~15 s of CPU to import).
"""

from steering_core.sae.training.rows import RowSource
from steering_core.sae.training.settings import TrainSettings
from steering_core.sae.training.trainer import train_sae

__all__ = ["RowSource", "TrainSettings", "train_sae"]
