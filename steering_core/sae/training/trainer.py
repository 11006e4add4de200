"""Train an SAE on a layer's residual rows with SAELens, into a folder SAELens and `load_sae` both read.

    <out_dir>/cfg.json, sae_weights.safetensors, sparsity.safetensors   SAELens's inference format
    <out_dir>/training.json                  ours, written last: identity, settings, final metrics
    <out_dir>/checkpoints/<samples>/         while training: sae.safetensors, trainer.pt, checkpoint.json

A finished folder of the same identity (rows, settings, SAELens version) is returned at once. A rerun
after a kill resumes from the latest complete checkpoint of the same identity (each is written under a
temporary name, then renamed) and, on the CPU, ends with the same bytes as an uninterrupted run: the row
stream restarts at the checkpoint's sample and nothing in training draws random numbers.
"""

from __future__ import annotations

import contextlib
import importlib.metadata
import io
import logging
import shutil
import time
from pathlib import Path
from typing import Any

from steering_core.devices import resolve_device
from steering_core.remote.locks import output_lock
from steering_core.reporting.progress import Progress, ProgressCallback
from steering_core.sae.formats import CFG_FILE, SPARSITY_FILE, WEIGHTS_FILE
from steering_core.sae.training.rows import RowSource
from steering_core.sae.training.settings import TrainSettings
from steering_core.storage.fileio import atomic_dir, atomic_files, json_text, read_json, sha256_json, write_json
from steering_core.tensor_files import load_safetensors, load_torch_file, save_safetensors, save_torch

logger = logging.getLogger(__name__)

FORMAT_VERSION = 1
TRAINING_FILE = "training.json"
CHECKPOINTS_DIR = "checkpoints"
CHECKPOINT_WEIGHTS = "sae.safetensors"  # the training SAE's state dict, buffers included
CHECKPOINT_STATE = "trainer.pt"  # optimiser, schedulers, counters, firing statistics (tensors and plain values)
CHECKPOINT_RECORD = "checkpoint.json"
FINAL_FILES = (WEIGHTS_FILE, SPARSITY_FILE, CFG_FILE, TRAINING_FILE)


def training_identity(source: RowSource, settings: TrainSettings, *, layer: int, model_name: str) -> str:
    """Return the sha256 of what the trained SAE depends on: the rows, the settings, the names, SAELens's version."""
    return sha256_json({"format_version": FORMAT_VERSION, "rows": source.identity(), "layer": layer,
                        "model_name": model_name, "settings": settings.model_dump(mode="json"),
                        "sae_lens": importlib.metadata.version("sae-lens")})


def train_sae(source: RowSource, out_dir: Path, settings: TrainSettings, *, layer: int, model_name: str = "pi05",
              progress: ProgressCallback | None = None) -> Path:
    """Train an SAE of `settings` on `source`'s rows into `out_dir` (see the module docstring); return `out_dir`.

    `progress(done, total)` counts rows seen. A shard holding NaN or Inf, or of another width than the run,
    stops training with a one-line ValueError naming the file; the final files are then left unwritten.
    """
    out_dir = Path(out_dir)
    if blocking := next((p for p in (out_dir, *out_dir.parents) if p.exists() and not p.is_dir()), None):
        raise NotADirectoryError(f"{blocking}: is a file, so the SAE folder {out_dir} cannot be written there; "
                                 "choose another output folder")
    identity = training_identity(source, settings, layer=layer, model_name=model_name)
    with output_lock(out_dir):  # a second run waits, then finds the folder finished
        if _finished(out_dir, identity):
            logger.info("%s: already trained with these rows and settings", out_dir)
            return out_dir
        try:
            _train(source, out_dir, settings, identity, layer=layer, model_name=model_name, progress=progress)
        except BaseException:
            with contextlib.suppress(OSError):  # nothing kept (e.g. a full disk at the first write): no empty folder
                out_dir.rmdir()
            raise
    return out_dir


def _train(source: RowSource, out_dir: Path, settings: TrainSettings, identity: str, *, layer: int, model_name: str,
           progress: ProgressCallback | None) -> None:
    """Train into `out_dir` (resuming from its latest checkpoint of this identity); write the final files."""
    device = resolve_device(settings.device)
    from steering_core.sae.training.loop import CheckpointingTrainer, build_sae  # SAELens is slow to import

    sae = build_sae(settings, source.width, layer=layer, model_name=model_name)
    checkpoints = out_dir / CHECKPOINTS_DIR
    with Progress(settings.training_rows, f"train SAE layer {layer}", "row", callback=progress,
                  stream=io.StringIO()) as bar:  # SAELens draws the terminal bar; ours logs and calls back
        trainer = CheckpointingTrainer(settings, sae, device, on_step=lambda done: bar.update(done - bar.done),
                                       on_checkpoint=lambda: _write_checkpoint(checkpoints, trainer, identity))
        resumed = _resume(checkpoints, identity, trainer)
        bar.update(resumed)
        scaling = None if settings.normalize == "none" else source.shuffled(
            settings.batch_size, seed=settings.seed, buffer_rows=settings.buffer_rows)
        trainer.start(source.shuffled(settings.batch_size, seed=settings.seed, buffer_rows=settings.buffer_rows,
                                      start_sample=resumed), scaling)
        start = time.perf_counter()
        trained = trainer.fit()
        seconds = time.perf_counter() - start
    _write_final(out_dir, trained, trainer, {
        "format_version": FORMAT_VERSION,
        "identity": identity,
        "sae_lens": importlib.metadata.version("sae-lens"),
        "source": {"run_dir": str(source.run_dir), "layer": source.layer, "token_type": source.token_type,
                   "episodes": list(source.episodes), "rows": source.rows, "width": source.width,
                   "identity": source.identity()},
        "settings": settings.model_dump(mode="json"),
        "device": str(device),
        "metrics": {**trainer.last_losses, "explained_variance_last_batch": trainer.last_explained_variance,
                    "l0": trained.cfg.metadata.l0, "dead_latents": trained.cfg.metadata.num_dead_features,
                    "rows_seen": trainer.n_training_samples, "steps": trainer.n_training_steps},
    })  # the same bytes for the same inputs: how long it took and where it resumed are logged only
    logger.info("%s: trained in %.1f s (%d rows seen, resumed from %d)", out_dir, seconds,
                trainer.n_training_samples, resumed)
    shutil.rmtree(checkpoints, ignore_errors=True)


def read_training_record(out_dir: Path) -> dict[str, Any]:
    """Return the `training.json` of a trained SAE folder."""
    return read_json(Path(out_dir) / TRAINING_FILE)


def _finished(out_dir: Path, identity: str) -> bool:
    """Return True if `out_dir` holds a finished SAE of this identity (one of another identity is trained again)."""
    record_path = out_dir / TRAINING_FILE
    if not record_path.is_file():
        return False
    if read_training_record(out_dir).get("identity") != identity:
        logger.info("%s: trained from other rows or settings; training again", out_dir)
        return False
    missing = [name for name in FINAL_FILES if not (out_dir / name).is_file()]
    if missing:
        logger.info("%s: %s missing, training again", out_dir, ", ".join(missing))
    return not missing


def _write_checkpoint(checkpoints: Path, trainer: Any, identity: str) -> None:
    """Write the trainer's state as checkpoints/<samples>/ (atomically), then remove the older checkpoints."""
    samples = trainer.n_training_samples
    weights = {name: tensor.detach().cpu().contiguous() for name, tensor in trainer.sae.state_dict().items()}
    with atomic_dir(checkpoints / str(samples), overwrite=True) as folder:
        folder.mkdir(parents=True)
        save_safetensors(weights, folder / CHECKPOINT_WEIGHTS)
        save_torch(trainer.state(), folder / CHECKPOINT_STATE)
        write_json(folder / CHECKPOINT_RECORD, {"format_version": FORMAT_VERSION, "identity": identity,
                                                "samples": samples})
    for older in _checkpoint_folders(checkpoints):
        if older.name != str(samples):
            shutil.rmtree(older, ignore_errors=True)
    logger.info("checkpoint at %d rows: %s", samples, checkpoints / str(samples))


def _resume(checkpoints: Path, identity: str, trainer: Any) -> int:
    """Load the latest checkpoint of this identity into the trainer; return its samples (0 when there is none).

    Checkpoints of another identity (a killed run with other rows or settings) are removed.
    """
    usable = []
    for folder in _checkpoint_folders(checkpoints):
        record_path = folder / CHECKPOINT_RECORD
        record = read_json(record_path) if record_path.is_file() else {}
        if record.get("identity") == identity and record.get("format_version") == FORMAT_VERSION:
            usable.append((int(record["samples"]), folder))
        else:
            logger.info("removing %s: a checkpoint of another training", folder)
            shutil.rmtree(folder, ignore_errors=True)
    if not usable:
        return 0
    samples, folder = max(usable)
    trainer.sae.load_state_dict(load_safetensors(folder / CHECKPOINT_WEIGHTS))
    trainer.load_state(load_torch_file(folder / CHECKPOINT_STATE))
    if trainer.n_training_samples != samples:
        raise ValueError(f"{folder / CHECKPOINT_STATE}: `n_training_samples` is {trainer.n_training_samples}, "
                         f"expected {samples} from its folder; remove {checkpoints} to train from the start")
    logger.info("resuming from %s (%d rows seen)", folder, samples)
    return samples


def _checkpoint_folders(checkpoints: Path) -> list[Path]:
    """Return the complete checkpoint folders (named by their samples; staging folders are hidden)."""
    if not checkpoints.is_dir():
        return []
    return sorted((p for p in checkpoints.iterdir() if p.is_dir() and p.name.isdigit()), key=lambda p: int(p.name))


def _write_final(out_dir: Path, sae: Any, trainer: Any, record: dict[str, Any]) -> None:
    """Write SAELens's three files and `training.json` as one output: all of them, or (on a failure) none."""
    from steering_core.sae.training.loop import inference_files

    weights, cfg, sparsity = inference_files(sae, trainer)
    texts = {CFG_FILE: json_text(_sorted_keys(cfg), out_dir / CFG_FILE),  # SAELens orders its fields by a set
             TRAINING_FILE: json_text(record, out_dir / TRAINING_FILE)}
    with atomic_files(out_dir) as staging:
        for name, tensors in ((WEIGHTS_FILE, weights), (SPARSITY_FILE, sparsity)):
            save_safetensors(tensors, staging / name)
        for name, text in texts.items():
            (staging / name).write_text(text, encoding="utf-8")


def _sorted_keys(value: Any) -> Any:
    """Return `value` with every mapping's keys in sorted order, so equal content gives equal bytes."""
    if isinstance(value, dict):
        return {key: _sorted_keys(value[key]) for key in sorted(value)}
    return value
