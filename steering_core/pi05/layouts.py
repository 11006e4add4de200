"""pi0.5 checkpoint layouts: openpi's converted PyTorch folder and lerobot's `PI05Policy` folder.

Both hold the same module tree under different key names (spec 1.2, 17.1). The rest of the package names every
tensor by openpi's key (the *canonical* name); a `Checkpoint` maps it to the name stored in its file, so the key
mapping of each layout lives here and nowhere else. The token embedding is the one tensor whose *source* differs:
openpi's file keeps the tied table once, as `lm_head`; lerobot's stores `embed_tokens` and `lm_head` as two
parameters and embeds with `embed_tokens` (its loader copies `lm_head` only into a file that lacks it).
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from enum import Enum
from pathlib import Path
from typing import Any

from steering_core.storage.fileio import read_json
from steering_core.tensor_files import check_safetensors

logger = logging.getLogger(__name__)

MODEL_FILE = "model.safetensors"
CONFIG_FILE = "config.json"
ASSETS_DIR = "assets"
LEROBOT_PREPROCESSOR = "policy_preprocessor.json"
LEROBOT_POSTPROCESSOR = "policy_postprocessor.json"
LEROBOT_TYPE = "pi05"  # lerobot's PI05Config registers itself under this `type`

# openpi's module tree (spec 1.2): the canonical names, concatenated directly with the suffixes in checkpoint.py
PALIGEMMA = "paligemma_with_expert.paligemma."
LM_PREFIX = PALIGEMMA + "model.language_model."
LM_HEAD_KEY = PALIGEMMA + "lm_head.weight"
EMBED_TOKENS_KEY = LM_PREFIX + "embed_tokens.weight"
# The canonical name of the token embedding table: openpi's file stores the tied table under this name.
EMBEDDING_KEY = LM_HEAD_KEY


class LayoutName(str, Enum):
    """A checkpoint layout the project reads; `auto` detects it from the folder."""

    AUTO = "auto"
    OPENPI = "openpi"
    LEROBOT = "lerobot"


@dataclass(frozen=True)
class CheckpointLayout:
    """How one library stores pi0.5: the key prefix of every tensor, the stored names of the token embedding in the
    order the library's loader prefers them, the parameters it keeps in float32 under a bfloat16 policy, and the
    folder files that mark it."""

    name: LayoutName
    prefix: str
    embedding_keys: tuple[str, ...]  # canonical names; the first one the file holds is the embedding table
    float32_selectors: tuple[str, ...]  # substrings of canonical names kept float32 when computing in bfloat16
    accumulated_time: bool  # the sampler's flow times: t += dt in float32 (openpi) or 1 + k*dt in float64 (lerobot)
    marks: str  # what a folder of this layout holds, for error messages

    def stored(self, canonical: str) -> str:
        """Return the name a canonical (openpi) key has in a file of this layout."""
        return self.prefix + canonical


_ADARMS_AND_HEADS = ("layernorm.dense", "norm.dense", "action_in_proj", "action_out_proj", "time_mlp_")

OPENPI = CheckpointLayout(
    name=LayoutName.OPENPI,
    prefix="",
    embedding_keys=(LM_HEAD_KEY,),
    # openpi's to_bfloat16_for_selected_params (spec 1.4, 10.6)
    float32_selectors=("embeddings.patch_embedding.weight", "embeddings.patch_embedding.bias",
                       "embeddings.position_embedding.weight", "input_layernorm", "post_attention_layernorm",
                       *_ADARMS_AND_HEADS),
    accumulated_time=True,
    marks=f"{MODEL_FILE} with bare openpi keys, {CONFIG_FILE} (action_dim, variants) and "
          f"{ASSETS_DIR}/<asset_id>/norm_stats.json",
)
LEROBOT = CheckpointLayout(
    name=LayoutName.LEROBOT,
    prefix="model.",
    embedding_keys=(EMBED_TOKENS_KEY, LM_HEAD_KEY),
    # lerobot's PaliGemmaWithExpertModel.to_bfloat16_for_selected_params keeps the whole vision path, the norms and
    # the expert's final norm in float32; the heads sit outside it and are never cast (spec 17.6)
    float32_selectors=("vision_tower", "multi_modal_projector", "input_layernorm", "post_attention_layernorm",
                       "model.norm", *_ADARMS_AND_HEADS),
    accumulated_time=False,
    marks=f"{MODEL_FILE} with every key prefixed 'model.', {CONFIG_FILE} (type: pi05), {LEROBOT_PREPROCESSOR} "
          f"and {LEROBOT_POSTPROCESSOR}",
)
LAYOUTS = {layout.name: layout for layout in (OPENPI, LEROBOT)}


@dataclass(frozen=True)
class Checkpoint:
    """A pi0.5 checkpoint on disk: its weights file, folder, layout, `config.json` and the stored name of its
    embedding table. Build it with `resolve_checkpoint`."""

    model_file: Path
    folder: Path
    layout: CheckpointLayout
    config: dict[str, Any] | None
    embedding: str  # stored name of the token embedding table

    def stored(self, canonical: str) -> str:
        """Return the name a canonical (openpi) key has in this file."""
        return self.embedding if canonical == EMBEDDING_KEY else self.layout.stored(canonical)

    def canonical(self, stored: str) -> str:
        """Return the canonical name of a stored key (the inverse of `stored` on the keys it maps)."""
        if stored == self.embedding:
            return EMBEDDING_KEY
        return stored.removeprefix(self.layout.prefix)

    @property
    def describe(self) -> str:
        """Return `<folder> (<layout> layout)` for logs and records."""
        return f"{self.model_file} ({self.layout.name.value} layout)"


def resolve_model_file(path: str | os.PathLike) -> Path:
    """Return the `model.safetensors` of a checkpoint folder, or `path` itself if it is that file."""
    path = Path(path)
    if path.is_dir():
        path = path / MODEL_FILE
    if not path.is_file():
        raise FileNotFoundError(
            f"{path}: pi0.5 checkpoint not found; pass a checkpoint folder (openpi's converted PyTorch checkpoint or "
            f"lerobot's PI05Policy folder, holding {MODEL_FILE}) or the .safetensors file itself"
        )
    return path


def resolve_checkpoint(path: str | os.PathLike, layout: LayoutName | str = LayoutName.AUTO) -> Checkpoint:
    """Return the checkpoint at `path` (folder or its model.safetensors) with its layout detected (or `layout`
    forced, then checked against the folder); one ValueError naming the file refuses a folder of an unknown layout,
    one that mixes two, a lerobot `config.json` that is not pi0.5, or a forced layout the folder contradicts."""
    layout = LayoutName(layout)
    model_file = resolve_model_file(path)
    folder = model_file.parent
    keys = list(check_safetensors(model_file).keys() - {"__metadata__"})
    by_keys = _layout_of_keys(model_file, keys)
    config = _read_config(folder / CONFIG_FILE)
    by_folder = _layout_of_folder(folder, config)
    if by_folder is not None and by_folder is not by_keys:
        raise ValueError(
            f"{folder}: the folder mixes two layouts: {model_file.name}'s keys are {by_keys.value}'s but "
            f"{_folder_evidence(folder, config)} is {by_folder.value}'s; expected one layout "
            f"({LAYOUTS[by_keys].marks})"
        )
    if layout is not LayoutName.AUTO and layout is not by_keys:
        raise ValueError(
            f"{model_file}: the layout was set to {layout.value}, but the file is {by_keys.value}'s "
            f"({LAYOUTS[by_keys].marks}); set the layout to {by_keys.value} or auto"
        )
    chosen = LAYOUTS[by_keys]
    embedding = _embedding_key(model_file, chosen, set(keys))
    checkpoint = Checkpoint(model_file, folder, chosen, config, embedding)
    logger.info("pi0.5 checkpoint %s: %s layout%s, token embedding %s", folder, chosen.name.value,
                " (detected)" if layout is LayoutName.AUTO else "", embedding)
    return checkpoint


def _layout_of_keys(model_file: Path, keys: list[str]) -> LayoutName:
    """Return the layout the tensor names show: every key under `model.` (lerobot) or none (openpi)."""
    prefixed = sum(key.startswith(LEROBOT.prefix) for key in keys)
    if not keys:
        raise ValueError(f"{model_file}: the file holds no tensors; expected a pi0.5 checkpoint")
    if prefixed == len(keys):
        return LayoutName.LEROBOT
    if prefixed == 0:
        if not any(key.startswith("paligemma_with_expert.") for key in keys):
            raise ValueError(
                f"{model_file}: no key starts with 'paligemma_with_expert.' or 'model.'; expected a pi0.5 "
                f"checkpoint in openpi's layout ({OPENPI.marks}) or lerobot's ({LEROBOT.marks})"
            )
        return LayoutName.OPENPI
    raise ValueError(
        f"{model_file}: {prefixed} of {len(keys)} keys start with 'model.' (lerobot's layout) and the others do not "
        "(openpi's): the file mixes two layouts; expected one"
    )


def _read_config(path: Path) -> dict[str, Any] | None:
    """Return `config.json` as an object, or None when the folder has none."""
    if not path.is_file():
        return None
    config = read_json(path)
    if not isinstance(config, dict):
        raise ValueError(f"{path}: expected a JSON object, found {type(config).__name__}")
    if "type" in config and config["type"] != LEROBOT_TYPE:
        raise ValueError(
            f"{path}: type {config['type']!r} is not pi0.5; expected {LEROBOT_TYPE!r} (lerobot's PI05Config) "
            "or an openpi pi0.5 checkpoint's config"
        )
    return config


def _layout_of_folder(folder: Path, config: dict[str, Any] | None) -> LayoutName | None:
    """Return the layout the folder's other files show, or None when they show none."""
    lerobot = (config is not None and config.get("type") == LEROBOT_TYPE) or any(
        (folder / name).is_file() for name in (LEROBOT_PREPROCESSOR, LEROBOT_POSTPROCESSOR))
    openpi = (config is not None and "type" not in config) or any((folder / ASSETS_DIR).glob("**/norm_stats.json"))
    if lerobot and openpi:
        raise ValueError(
            f"{folder}: the folder mixes two layouts: {_folder_evidence(folder, config)}; expected openpi's "
            f"({OPENPI.marks}) or lerobot's ({LEROBOT.marks}), not both"
        )
    return LayoutName.LEROBOT if lerobot else LayoutName.OPENPI if openpi else None


def _folder_evidence(folder: Path, config: dict[str, Any] | None) -> str:
    """Return which of the folder's files mark a layout, e.g. `config.json (type pi05), assets/.../norm_stats.json`."""
    found = []
    if config is not None:
        found.append(f"{CONFIG_FILE} ({'type ' + config['type'] if 'type' in config else 'openpi fields'})")
    found += [name for name in (LEROBOT_PREPROCESSOR, LEROBOT_POSTPROCESSOR) if (folder / name).is_file()]
    found += [str(p.relative_to(folder)) for p in sorted((folder / ASSETS_DIR).glob("**/norm_stats.json"))]
    return ", ".join(found)


def _embedding_key(model_file: Path, layout: CheckpointLayout, keys: set[str]) -> str:
    """Return the stored name of the token embedding table, as the layout's own loader picks it."""
    stored = [layout.stored(name) for name in layout.embedding_keys]
    present = [name for name in stored if name in keys]
    if layout is OPENPI and EMBED_TOKENS_KEY in keys:
        raise ValueError(
            f"{model_file}: holds both {LM_HEAD_KEY} and {EMBED_TOKENS_KEY} without lerobot's 'model.' prefix; "
            "openpi's files keep the tied table once (as lm_head): re-save it in one layout"
        )
    if not present:
        return stored[0]  # reported with every other missing tensor when the prefix is checked
    if present[0] != stored[0]:
        logger.warning("%s: no %s; embedding tokens with %s, as lerobot's loader does (it copies lm_head into "
                       "embed_tokens when the file lacks it)", model_file, stored[0], present[0])
    return present[0]
