"""The run config: one YAML file describing a whole pipeline run, composed of every step's own settings.

```yaml
name: drawer_stove                # residuals/<name>/
output_root: data                 # the seed's data/ folder; relative paths resolve against this file
sources:
  folders: [/data/libero_90]      # the *.hdf5 files directly inside
  select: {match: ignore_case}    # FilterSettings; no tasks/globs = the pairs' task texts
dataset: {repo_id: libero_drawer_stove_lerobot}   # ConvertSettings fields (+ optional root)
# or, instead of `sources`, an existing LeRobot dataset (v2.0/v2.1/v3.0) read in place, never written:
# dataset: {existing: /data/physical-intelligence/libero, repo_id: physical-intelligence/libero}
pairs:
  - {name: open_vs_close, positive: open the top drawer of the cabinet,
     negative: close the top drawer of the cabinet}
  - {name: on_vs_off, positive: turn on the stove, negative: turn off the stove,
     manifest: {pad: 8}, rename: {turn on the stove: stove_on}}
layers: [12]
model: {checkpoint: /ckpt/pi05_libero_pytorch, tokenizer: /ckpt/paligemma_tokenizer.model}
capture: {batch_size: 64, storage_dtype: bfloat16}   # CaptureSettings without model paths and layers
slicing: {reduce: token}                             # SliceSettings without layers and token type
sae: {12: {release: gemma-2b-it-res-jb}}             # per layer; absent or null: residual space only
steering: {batch_size: 512, top_k: 20}               # SteeringSettings without paths, layer and SAE
evaluate: {holdout_fraction: 0.2, max_frames: 32}    # EvaluateSettings without top_k; null: no phase 4
# evaluate: {expert_layers: [9]}   # also capture `decision` rows at these action-expert layers and evaluate them
```

Sections that reuse a step's settings model take its fields minus those the run config supplies
(paths under `output_root`, `layers`, the model and SAE sections); the full settings of each step
are built by `RunConfig.*_settings()`, so the pipeline and the CLI steps always agree. Errors from
`load_run_config` name the file and the key path: `run.yaml: pairs[1].positive: field required`.
"""

from __future__ import annotations

import copy
import os
import re
from collections.abc import Mapping
from pathlib import Path
from typing import Annotated, Any, Literal

import yaml
from pydantic import (
    AfterValidator,
    Field,
    ValidationError,
    ValidationInfo,
    create_model,
    field_validator,
    model_validator,
)

from steering_core.capture import CaptureSettings
from steering_core.capture.slicing import SliceSettings
from steering_core.data.contrast import ContrastSettings
from steering_core.data.convert import ConvertSettings
from steering_core.data.filtering import FilterSettings
from steering_core.evaluate import EvaluateSettings
from steering_core.pi05 import Pi05Arch
from steering_core.sae.vectors import PairsConfig, PairSpec, SteeringSettings
from steering_core.storage import layout
from steering_core.storage.fileio import atomic_path
from steering_core.storage.schema import StrictModel

CONFIG_FILE = "run.yaml"  # name used when a run config is written next to its outputs
PAIRS_CONFIG_FILE = "{layer_dir}_pairs.json"  # the seed's data/latent_steering/layer12_pairs.json
_SAFE_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]*$")
# Step settings the run config supplies itself, and where to set them instead.
_SUPPLIED = {
    "capture": {"checkpoint_path": "model.checkpoint", "tokenizer_path": "model.tokenizer",
                "norm_stats_path": "model.norm_stats", "arch": "model.arch", "layers": "layers"},
    "slicing": {"layers": "layers", "token_type": "capture.token_type", "holdout_episodes": "evaluate.holdout_fraction"},
    "steering": {"pairs_config": "pairs", "output_root": "output_root", "layer": "layers", "sae": "sae.<layer>",
                 "sae_id": "sae.<layer>.sae_id", "sae_dir": "sae.<layer>.local_dir",
                 "sae_cfg_from": "sae.<layer>.cfg_from", "paths_relative_to": "output_root"},
    "evaluate": {"top_k": "steering.top_k"},
}


def _resolve_path(value: Path, info: ValidationInfo) -> Path:
    """Return `value` made absolute against the config file's folder (validation context `base_dir`)."""
    value = value.expanduser()
    base = (info.context or {}).get("base_dir")
    return value if value.is_absolute() or base is None else Path(base) / value


ConfigPath = Annotated[Path, AfterValidator(_resolve_path)]


def options_model(settings: type[StrictModel], supplied: tuple[str, ...], name: str, **extra: Any) -> type[StrictModel]:
    """Return a model with the fields of `settings` minus `supplied` (plus `extra`): a config section.

    Fields keep their types, defaults and constraints, so a section is checked where it is written;
    the full settings model (with its own validators) is built later from section + supplied values.
    """
    unknown = set(supplied) - set(settings.model_fields)
    if unknown:
        raise TypeError(f"{settings.__name__} has no fields {sorted(unknown)}")
    fields: dict[str, Any] = {
        key: (info.annotation, copy.copy(info)) for key, info in settings.model_fields.items() if key not in supplied
    }
    return create_model(name, __base__=StrictModel, __doc__=f"{settings.__name__} minus {', '.join(supplied)}.",
                        **fields, **extra)


# Sections derived from the steps' own settings (the run config supplies the removed fields).
_ConvertOptions = options_model(ConvertSettings, (), "_ConvertOptions", root=(ConfigPath | None, None))
CaptureSection = options_model(CaptureSettings, tuple(_SUPPLIED["capture"]), "CaptureSection")
SliceSection = options_model(SliceSettings, tuple(_SUPPLIED["slicing"]), "SliceSection")
SteeringSection = options_model(SteeringSettings, tuple(_SUPPLIED["steering"]), "SteeringSection")


def _expert_layers(layers: tuple[int, ...]) -> tuple[int, ...]:
    """Return the expert layers sorted and without repeats; refuse negative ones."""
    if any(layer < 0 for layer in layers):
        raise ValueError(f"expert_layers {list(layers)} include a negative index; expert layers count from 0")
    return tuple(sorted(set(layers)))


# The evaluation settings plus the run-level choice of action-expert layers: capturing their `decision` rows is
# a second capture run, so the list belongs to the run config, not to each (pair, layer) evaluation.
EvaluateSection = options_model(
    EvaluateSettings, tuple(_SUPPLIED["evaluate"]), "EvaluateSection",
    expert_layers=(Annotated[tuple[int, ...], AfterValidator(_expert_layers)], ()),
)


class DatasetSection(_ConvertOptions):
    """The LeRobot dataset of the run: converted from `sources` (ConvertSettings fields, optional `root`
    to write it elsewhere), or an `existing` dataset folder read in place, never written into."""

    existing: ConfigPath | None = None   # a LeRobot v2.0/v2.1/v3.0 dataset root (a read-only HF cache is fine)
    repo_id: str | None = Field(None, min_length=1)  # existing: defaults to the folder's name

    @model_validator(mode="after")
    def _existing_or_converted(self) -> DatasetSection:
        if self.existing is None:
            if self.repo_id is None:
                raise ValueError("give `repo_id` (the name of the dataset converted from `sources`), "
                                 "or `existing` with the path of a LeRobot dataset to read in place")
            return self
        if converting := sorted(self.model_fields_set - {"existing", "repo_id"}):
            raise ValueError(f"{converting} apply only when converting hdf5 `sources`; an `existing` dataset "
                             "is read as it is: remove them")
        return self

    @property
    def name(self) -> str:
        """Return the dataset's repo id: as given, else the existing folder's name."""
        return self.repo_id or self.existing.name


class SourcesSection(StrictModel):
    """Where demo files come from and which are selected."""

    folders: tuple[ConfigPath, ...] = Field(min_length=1)
    select: FilterSettings = FilterSettings()  # no tasks and no globs: the task texts of the pairs
    suite: str = Field("demos", pattern=_SAFE_NAME.pattern)  # libero_filtered/<suite>/


class PairSection(StrictModel):
    """One concept pair: two task texts of the dataset, contrasted by a manifest."""

    name: str = Field(pattern=_SAFE_NAME.pattern)  # folder and file names: manifests/<name>.json
    positive: str = Field(min_length=1)            # task text of the positive concept (task A)
    negative: str = Field(min_length=1)            # task text of the negative concept (task B)
    rename: dict[str, str] = {}                    # task text -> concept name, as in the seed
    manifest: ContrastSettings = ContrastSettings()

    @model_validator(mode="after")
    def _two_tasks(self) -> PairSection:
        if self.positive.strip().casefold() == self.negative.strip().casefold():
            raise ValueError(f"positive and negative are both {self.positive!r}; a pair needs two different tasks")
        return self

    def concept(self, task: str) -> str:
        """Return the concept name of one of the pair's task texts (after `rename`)."""
        return self.rename.get(task, task)


class ModelSection(StrictModel):
    """The pi0.5 checkpoint and what reads it."""

    checkpoint: ConfigPath                 # openpi PyTorch checkpoint folder or its model.safetensors
    tokenizer: ConfigPath                  # PaliGemma SentencePiece model
    norm_stats: ConfigPath | None = None   # discrete-state prompts only; default: the checkpoint's assets
    arch: Pi05Arch = Pi05Arch()            # real pi0.5 dimensions; tiny models pass theirs


class SaeSection(StrictModel):
    """One layer's SAE: a release of the registry (+ sae id) or a path (folder or state dict)."""

    release: str | None = None
    sae_id: str | None = None              # default blocks.<layer>.hook_resid_post
    path: ConfigPath | None = None
    local_dir: ConfigPath | None = None    # folder of release folders, searched before the HF cache
    cfg_from: str | None = None            # state-dict SAE: folder or release whose cfg.json applies

    @model_validator(mode="after")
    def _one_source(self) -> SaeSection:
        if (self.release is None) == (self.path is None):
            raise ValueError("give exactly one of `release` (with optional `sae_id`) or `path`")
        if self.sae_id is not None and self.release is None and self.cfg_from is None:
            raise ValueError("`sae_id` needs `release` (or `cfg_from` for a state dict)")
        return self

    @property
    def source(self) -> str:
        """Return what `steering_core.sae.load_sae` takes as its source."""
        return self.release if self.release is not None else str(self.path)


class OrchestrationSection(StrictModel):
    """How the Prefect flows run the steps (no effect on any output)."""

    capture: Literal["auto", "deployment", "local"] = "auto"  # GPU phases (capture, evaluate): auto = deployments
    capture_deployment: str = "latent-steering-capture/gpu"  # when run from one
    evaluate_deployment: str = "latent-steering-evaluate/gpu-evaluate"
    pipeline_deployment: str = "latent-steering/pipeline"     # what a scheduled refresh starts
    shards_per_capture_run: int = Field(8, ge=1)  # episode groups per GPU flow run (one model load each)
    poll_seconds: float = Field(5.0, gt=0)        # how often the parent checks its capture runs
    worker_wait_seconds: float = Field(600.0, gt=0)  # capture runs still unstarted, no gpu worker online: fail


class RunConfig(StrictModel):
    """A whole pipeline run: sources -> dataset -> manifests -> capture -> slices -> steering vectors."""

    name: str = Field("run", pattern=_SAFE_NAME.pattern)  # residuals/<name>/
    output_root: ConfigPath = Field(Path("data"), validate_default=True)
    sources: SourcesSection | None = None  # hdf5 demos to filter and convert; None with `dataset.existing`
    dataset: DatasetSection
    pairs: tuple[PairSection, ...] = Field(min_length=1)
    layers: tuple[int, ...] = Field((12,), min_length=1)  # the seed's SAE layer
    model: ModelSection
    capture: CaptureSection = CaptureSection()
    slicing: SliceSection = SliceSection()
    sae: dict[int, SaeSection | None] = {}
    steering: SteeringSection = SteeringSection()
    evaluate: EvaluateSection | None = EvaluateSection()  # null: no phase 4 and no held-out episodes
    orchestration: OrchestrationSection = OrchestrationSection()

    @field_validator("pairs")
    @classmethod
    def _unique_pairs(cls, pairs: tuple[PairSection, ...]) -> tuple[PairSection, ...]:
        seen: dict[str, int] = {}
        for i, pair in enumerate(pairs):
            if pair.name in seen:
                raise ValueError(f"pairs[{seen[pair.name]}] and pairs[{i}] are both named {pair.name!r}; names must be unique")
            seen[pair.name] = i
        return pairs

    @field_validator("layers")
    @classmethod
    def _sorted_layers(cls, layers: tuple[int, ...]) -> tuple[int, ...]:
        if any(layer < 0 for layer in layers):
            raise ValueError(f"layers {list(layers)} include a negative index; decoder layers count from 0")
        return tuple(sorted(set(layers)))

    @model_validator(mode="after")
    def _consistent(self) -> RunConfig:
        problems = []
        depth = self.model.arch.depth
        if too_deep := [layer for layer in self.layers if layer >= depth]:
            problems.append(f"layers {too_deep} out of range: model.arch has {depth} decoder layers (0..{depth - 1})")
        if stray := sorted(set(self.sae) - set(self.layers)):
            problems.append(f"sae has entries for layers {stray} that are not in layers {list(self.layers)}")
        if self.expert_layers:
            if too_deep := [layer for layer in self.expert_layers if layer >= depth]:
                problems.append(f"evaluate.expert_layers {too_deep} out of range: the action expert has {depth} "
                                f"decoder layers (0..{depth - 1}), as many as model.arch.depth")
            if self.capture.num_steps != self.evaluate.num_steps:
                problems.append(f"evaluate.num_steps {self.evaluate.num_steps} differs from capture.num_steps "
                                f"{self.capture.num_steps}: the expert direction comes from the decision rows of "
                                "the sampler the evaluation steers; set both to the same value")
        if (self.sources is None) == (self.dataset.existing is None):
            problems.append("give exactly one of `sources` (hdf5 demo folders to filter and convert) and "
                            f"`dataset.existing` (a LeRobot dataset to read in place); found "
                            f"{'both' if self.sources is not None else 'neither'}")
        if problems:
            raise ValueError("; ".join(problems))
        return self

    # ------------------------------------------------------------------ paths (the seed's layout)

    @property
    def converts(self) -> bool:
        """Return True when the run filters and converts hdf5 `sources`, False for an existing dataset."""
        return self.dataset.existing is None

    @property
    def repo_id(self) -> str:
        """Return the dataset's repo id (manifests and capture records name it)."""
        return self.dataset.name

    @property
    def filtered_dir(self) -> Path:
        """Return the folder of selected demo files (links) and selection.json."""
        return self.output_root / layout.FILTERED_DIR.format(suite=self._sources().suite)

    @property
    def dataset_root(self) -> Path:
        """Return the LeRobot dataset folder: the existing one, or the one converted from `sources`."""
        if self.dataset.existing is not None:
            return self.dataset.existing
        return self.dataset.root or self.output_root / layout.LEROBOT_DIR.format(repo_id=self.dataset.repo_id)

    def _sources(self) -> SourcesSection:
        """Return the hdf5 sources; ValueError when the run reads an existing dataset instead."""
        if self.sources is None:
            raise ValueError(f"the run reads the existing dataset {self.dataset.existing} in place: "
                             "it has no hdf5 `sources` to filter or convert")
        return self.sources

    def manifest_path(self, pair: PairSection) -> Path:
        """Return `manifests/<pair>.json`."""
        return self.output_root / layout.MANIFEST_FILE.format(pair=pair.name)

    def concept_map_path(self, pair: PairSection) -> Path:
        """Return `manifests/<pair>_concept_map.json`."""
        return self.output_root / layout.CONCEPT_MAP_FILE.format(pair=pair.name)

    @property
    def run_dir(self) -> Path:
        """Return the residual run folder `residuals/<name>`."""
        return self.output_root / layout.RESIDUALS_RUN_DIR.format(run=self.name)

    def split_path(self, pair: PairSection) -> Path:
        """Return `manifests/<pair>_split.json` (held-out episodes per task)."""
        return self.output_root / layout.SPLIT_FILE.format(pair=pair.name)

    @property
    def holdout_fraction(self) -> float:
        """Return the share of each task's episodes held out of slicing (0 without an evaluate section)."""
        return self.evaluate.holdout_fraction if self.evaluate is not None else 0.0

    def slices_dir(self, pair: PairSection) -> Path:
        """Return `residuals/<pair>_slices` (holding layerNN/<concept>.pt)."""
        return self.output_root / layout.SLICES_DIR.format(pair=pair.name)

    @property
    def expert_layers(self) -> tuple[int, ...]:
        """Return the action-expert layers whose `decision` rows are captured and evaluated (empty: none)."""
        return self.evaluate.expert_layers if self.evaluate is not None else ()

    @property
    def decision_run_dir(self) -> Path:
        """Return the `decision` residual run folder `residuals/<name>_decision` (evaluate.expert_layers)."""
        return self.output_root / layout.DECISION_RUN_DIR.format(run=self.name)

    def decision_slices_dir(self, pair: PairSection) -> Path:
        """Return `residuals/<pair>_decision_slices` (holding layerKK/<concept>.pt of expert layer KK)."""
        return self.output_root / layout.DECISION_SLICES_DIR.format(pair=pair.name)

    @property
    def steering_root(self) -> Path:
        """Return `latent_steering/` (holding layerNN/<pair>/ and the per-layer reports)."""
        return self.output_root / layout.STEERING_ROOT

    def layer_path(self, layer: int) -> Path:
        """Return `latent_steering/layerNN`."""
        return self.steering_root / layout.layer_dir(layer)

    def pairs_config_path(self, layer: int) -> Path:
        """Return the seed's pairs config of one layer, `latent_steering/layerNN_pairs.json`."""
        return self.steering_root / PAIRS_CONFIG_FILE.format(layer_dir=layout.layer_dir(layer))

    @property
    def eval_root(self) -> Path:
        """Return `steering_eval/` (phase 4: layerNN/<pair>/ and the per-layer summaries)."""
        return self.output_root / layout.STEERING_EVAL_ROOT

    def eval_layer_path(self, layer: int, stream: str = "lm") -> Path:
        """Return `steering_eval/layerNN` or, for the action expert, `steering_eval/expert_layerKK`
        (holding <pair>/dose_response.* and the layer summary)."""
        return self.eval_root / layout.stream_layer_dir(layer, stream)

    def eval_layers(self) -> list[tuple[int, str]]:
        """Return every evaluated (layer, stream): the language model's layers, then the expert's."""
        if self.evaluate is None:
            return []
        return [(layer, "lm") for layer in self.layers] + [(layer, "expert") for layer in self.expert_layers]

    def pair(self, name: str) -> PairSection:
        """Return the pair called `name`."""
        for pair in self.pairs:
            if pair.name == name:
                return pair
        raise ValueError(f"no pair named {name!r}; the run config has {[p.name for p in self.pairs]}")

    # ------------------------------------------------------------------ each step's settings

    def filter_settings(self) -> FilterSettings:
        """Return the demo selection; with no tasks and no globs, the task texts of every pair."""
        select = self._sources().select
        if select.tasks or select.globs:
            return select
        tasks = dict.fromkeys(text for pair in self.pairs for text in (pair.positive, pair.negative))
        return select.model_copy(update={"tasks": tuple(tasks)})

    def convert_settings(self) -> ConvertSettings:
        """Return the LIBERO -> LeRobot conversion settings."""
        self._sources()
        return ConvertSettings(**self.dataset.model_dump(exclude={"root", "existing"}))

    def capture_settings(self) -> CaptureSettings:
        """Return the capture settings: the capture section plus model paths and layers."""
        return CaptureSettings(
            **self.capture.model_dump(),
            checkpoint_path=self.model.checkpoint,
            tokenizer_path=self.model.tokenizer,
            norm_stats_path=self.model.norm_stats,
            arch=self.model.arch,
            layers=self.layers,
        )

    def decision_capture_settings(self) -> CaptureSettings:
        """Return the settings of the `decision` capture: the main capture's at the expert layers."""
        if not self.expert_layers:
            raise ValueError("evaluate.expert_layers is empty: the run captures no decision rows")
        return CaptureSettings(**(self.capture_settings().model_dump() | {"token_type": "decision",
                                                                           "layers": self.expert_layers}))

    def slice_settings(self, layer: int, holdout_episodes: tuple[int, ...] = (), stream: str = "lm") -> SliceSettings:
        """Return the slicing settings of one layer (of the language model, or the expert's decision rows),
        leaving out a pair's held-out episodes."""
        token_type = "decision" if stream == "expert" else self.capture.token_type
        return SliceSettings(**self.slicing.model_dump(), layers=(layer,), token_type=token_type,
                             holdout_episodes=tuple(sorted(holdout_episodes)))

    def sae_for(self, layer: int) -> SaeSection | None:
        """Return the SAE configured for `layer`, or None (residual-space directions only)."""
        return self.sae.get(layer)

    def steering_settings(self, layer: int) -> SteeringSettings:
        """Return the steering settings of one layer (pairs config and outputs under output_root)."""
        sae = self.sae_for(layer)
        return SteeringSettings(
            **self.steering.model_dump(),
            pairs_config=self.pairs_config_path(layer),
            output_root=self.steering_root,
            layer=layer,
            sae=None if sae is None else sae.source,
            sae_id=None if sae is None else sae.sae_id,
            sae_dir=None if sae is None else sae.local_dir,
            sae_cfg_from=None if sae is None else sae.cfg_from,
            paths_relative_to="config",
        )

    def evaluate_settings(self) -> EvaluateSettings:
        """Return the evaluation settings (top-k from the steering section); raise when evaluation is off."""
        if self.evaluate is None:
            raise ValueError("the run config has `evaluate: null`; add an evaluate section to evaluate the vectors")
        return EvaluateSettings(**self.evaluate.model_dump(exclude={"expert_layers"}), top_k=self.steering.top_k)

    def pairs_config(
        self, layer: int, tasks: Mapping[str, tuple[str, str]], slices: Mapping[str, Mapping[str, str]]
    ) -> PairsConfig:
        """Return the seed's pairs config of one layer, with paths relative to its own folder.

        `tasks` maps a pair to its (positive, negative) task texts as the dataset spells them;
        `slices` maps a pair to concept name -> slice `.pt` file.
        """
        base = self.pairs_config_path(layer).parent
        specs = []
        for pair in self.pairs:
            (positive, negative), files = tasks[pair.name], slices[pair.name]
            labels = pair.concept(positive), pair.concept(negative)
            missing = [label for label in labels if label not in files]
            if missing:
                raise ValueError(f"pair {pair.name!r}: no slice for concept(s) {missing}; the slices hold {sorted(files)}")
            specs.append(PairSpec(
                name=pair.name,
                positive_label=labels[0], positive_path=os.path.relpath(files[labels[0]], base),
                negative_label=labels[1], negative_path=os.path.relpath(files[labels[1]], base),
            ))
        return PairsConfig(pairs=specs)


# ----------------------------------------------------------------------------- YAML

def load_run_config(path: str | os.PathLike) -> RunConfig:
    """Return the validated run config of a YAML file; relative paths resolve against its folder.

    Raises FileNotFoundError when the file is missing, ValueError listing every problem as
    `<file>: <key path>: <message>` otherwise.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: run config not found; pass --config with a YAML file (see README)")
    try:
        data = yaml.safe_load(path.read_text(encoding="utf-8"))
    except yaml.YAMLError as err:
        mark = getattr(err, "problem_mark", None)
        where = f"line {mark.line + 1}, column {mark.column + 1}: " if mark is not None else ""
        raise ValueError(f"{path}: not valid YAML ({where}{getattr(err, 'problem', None) or err})") from None
    if not isinstance(data, dict):
        raise ValueError(f"{path}: expected a mapping of sections (sources, dataset, pairs, ...), found {type(data).__name__}")
    try:
        return RunConfig.model_validate(data, context={"base_dir": path.resolve().parent})
    except ValidationError as err:
        raise ValueError("\n".join(f"{path}: {line}" for line in format_errors(err, data))) from None


def format_errors(err: ValidationError, data: Any = None) -> list[str]:
    """Return one `key path: message` line per validation error, e.g. `pairs[1].positive: field required`.

    With the validated `data`, list positions print as `[i]` and mapping keys as `.key` (`sae.12`).
    """
    lines = []
    for error in err.errors(include_url=False):
        key = _key_path(error["loc"], data)
        message = error["msg"].removeprefix("Value error, ")
        message = message[:1].lower() + message[1:]
        if error["type"] == "extra_forbidden":
            section, _, field = key.partition(".")
            instead = _SUPPLIED.get(section, {}).get(field)
            message = f"set by the run config: use `{instead}`" if instead else "unknown key (check its spelling and section)"
        lines.append(f"{key}: {message}" if key else message)
    return lines


def _key_path(loc: tuple[Any, ...], data: Any) -> str:
    """Return a YAML key path for an error location: `pairs[1].manifest.pad`."""
    parts, node = [], data
    for part in loc:
        in_list = isinstance(node, list) or (node is None and isinstance(part, int))
        parts.append(f"[{part}]" if in_list else f".{part}")
        try:
            node = node[part] if isinstance(node, (list, dict)) else None
        except (IndexError, KeyError):
            node = None
    return "".join(parts).lstrip(".")


def write_run_config(config: RunConfig, path: str | os.PathLike) -> Path:
    """Write `config` as YAML (absolute paths, non-default values only) and return the path."""
    path = Path(path)
    payload = config.model_dump(mode="json", exclude_defaults=True)
    with atomic_path(path) as tmp:
        tmp.write_text(yaml.safe_dump(payload, sort_keys=False, allow_unicode=True), encoding="utf-8")
    return path
