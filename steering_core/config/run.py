"""`RunConfig`: a whole pipeline run, its outputs at the seed's paths under `output_root`, and the full
settings of each step built from its section plus what the run supplies."""

from __future__ import annotations

import os
import re
from collections.abc import Mapping
from pathlib import Path

from pydantic import Field, field_validator, model_validator

from steering_core import layout
from steering_core.capture import CaptureSettings
from steering_core.capture.slicing import SliceSettings
from steering_core.config.sections import (
    MAX_NAME_CHARS,
    SAFE_NAME,
    CaptureSection,
    DatasetSection,
    EvaluateSection,
    ModelSection,
    OrchestrationSection,
    OutputPath,
    PairSection,
    RolloutSection,
    SaeSection,
    SliceSection,
    SourcesSection,
    SteeringSection,
)
from steering_core.data.convert import ConvertSettings
from steering_core.data.filtering import FilterSettings
from steering_core.evaluate import EvaluateSettings
from steering_core.pi05.robot_side import DEFAULT_HORIZON
from steering_core.pi05.spec import ModelSpec
from steering_core.sae.training.settings import TrainSettings
from steering_core.storage.overwrites import overwrite_problem
from steering_core.storage.schema import StrictModel
from steering_core.vectors.directions import PairsConfig, PairSpec, SteeringSettings
from steering_core.workload import evaluation_problems, rollout_problems

PAIRS_CONFIG_FILE = "{layer_dir}_pairs.json"  # the seed's data/latent_steering/layer12_pairs.json


class RunConfig(StrictModel):
    """A whole pipeline run: sources -> dataset -> manifests -> capture -> slices -> steering vectors."""

    name: str = Field("run", pattern=SAFE_NAME.pattern, max_length=MAX_NAME_CHARS)  # residuals/<name>/
    output_root: OutputPath = Field(Path("data"), validate_default=True)
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
    rollout: RolloutSection | None = None  # phase 5: closed-loop LIBERO episodes of the pairs it maps to tasks
    orchestration: OrchestrationSection = OrchestrationSection()

    @field_validator("pairs")
    @classmethod
    def _unique_pairs(cls, pairs: tuple[PairSection, ...]) -> tuple[PairSection, ...]:
        seen: dict[str, int] = {}
        tasks: dict[frozenset[str], int] = {}
        for i, pair in enumerate(pairs):
            if pair.name in seen:
                raise ValueError(f"pairs[{seen[pair.name]}] and pairs[{i}] are both named {pair.name!r}; names must be unique")
            seen[pair.name] = i
            both = frozenset(text.strip().casefold() for text in (pair.positive, pair.negative))
            if both in tasks:
                raise ValueError(f"pairs[{tasks[both]}] and pairs[{i}] ({pair.name!r}) contrast the same two tasks "
                                 f"{pair.positive!r} and {pair.negative!r}; give each pair of tasks once")
            tasks[both] = i
        return pairs

    @field_validator("sae", mode="before")
    @classmethod
    def _one_key_per_layer(cls, sae: object) -> object:
        """Refuse two keys of one layer (`1` and `'1'`, which would merge) and a layer spelled otherwise (`'01'`)."""
        if not isinstance(sae, dict):
            return sae
        seen: dict[int, object] = {}
        for key in sae:
            if isinstance(key, str) and re.fullmatch(r"\s*[+-]?\d+\s*", key) and key != str(int(key)):
                raise ValueError(f"key {key!r}: expected a layer number written as one, e.g. {int(key)}")
            layer = int(key) if isinstance(key, str) and re.fullmatch(r"-?\d+", key) else key
            if layer in seen and not isinstance(layer, bool):
                raise ValueError(f"keys {seen[layer]!r} and {key!r} both name layer {layer}; keep one")
            seen[layer] = key
        return sae

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
        if self.evaluate is not None and depth - 1 in self.layers:
            problems.append(f"layers include {depth - 1}, the last decoder layer: its output only feeds the final "
                            "norm the actions never read, so steering it cannot move them; evaluate earlier layers "
                            "or set `evaluate: null`")
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
        if self.rollout is not None and (stray := sorted(set(self.rollout.pairs) - {p.name for p in self.pairs})):
            problems.append(f"rollout.pairs names {stray}, not pairs of this run ({[p.name for p in self.pairs]})")
        if self.rollout is not None and self.rollout.layers is not None and (
                stray := sorted(set(self.rollout.layers) - set(self.layers))):
            problems.append(f"rollout.layers {stray} are not layers of this run ({list(self.layers)})")
        if self.rollout is not None and depth - 1 in self.rollout_layers:
            problems.append(f"layers include {depth - 1}, the last decoder layer: steering it cannot move the actions, "
                            "so its rollouts would only repeat α = 0; roll out earlier layers")
        if (overlap := run_overwrite_problem(self)) is not None:
            problems.append(overlap)
        problems += self._workload_problems()
        if (self.sources is None) == (self.dataset.existing is None):
            problems.append("give exactly one of `sources` (hdf5 demo folders to filter and convert) and "
                            f"`dataset.existing` (a LeRobot dataset to read in place); found "
                            f"{'both' if self.sources is not None else 'neither'}")
        if problems:
            raise ValueError("; ".join(problems))
        return self

    def _workload_problems(self) -> list[str]:
        """Return the evaluation's and the rollouts' estimated work over its limit (`steering_core.workload`)."""
        problems = rollout_problems(self)
        if self.evaluate is not None:
            problems += evaluation_problems(self.evaluate_settings(), self.model.action_horizon or DEFAULT_HORIZON)
        return problems

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

    @property
    def rollout_root(self) -> Path:
        """Return `rollouts/` (phase 5: layerNN/<pair>/<cell>/ and the per-layer summaries)."""
        return self.output_root / layout.ROLLOUTS_ROOT

    def rollout_layer_path(self, layer: int) -> Path:
        """Return `rollouts/layerNN`."""
        return self.rollout_root / layout.layer_dir(layer)

    @property
    def rollout_layers(self) -> tuple[int, ...]:
        """Return the layers rolled out (none without a rollout section)."""
        if self.rollout is None:
            return ()
        return self.layers if self.rollout.layers is None else tuple(sorted(set(self.rollout.layers)))

    def rollout_targets(self) -> list[tuple[str, int]]:
        """Return every rolled-out (pair, layer), layer by layer, in the config's pair order."""
        return [(pair.name, layer) for layer in self.rollout_layers for pair in self.pairs
                if pair.name in self.rollout.pairs]

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
        return CaptureSettings(**self.capture.model_dump(), model=ModelSpec(**self.model.model_dump()), layers=self.layers)

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

    @property
    def trained_layers(self) -> tuple[int, ...]:
        """Return the layers whose SAE is trained on this run's residuals (`sae.<layer>.train`)."""
        return tuple(layer for layer in self.layers if (sae := self.sae_for(layer)) is not None and sae.train)

    def sae_layer_path(self, layer: int) -> Path:
        """Return `saes/<name>/layerNN` (the trained SAE's judgement and feature pages)."""
        return self.output_root / layout.SAES_DIR.format(run=self.name) / layout.layer_dir(layer)

    def trained_sae_dir(self, layer: int) -> Path:
        """Return `saes/<name>/layerNN/sae`, the trained SAE in SAELens's format."""
        return self.sae_layer_path(layer) / layout.TRAINED_SAE_DIR

    def train_settings(self, layer: int) -> TrainSettings:
        """Return the training settings of one layer; raise when its SAE is not trained."""
        sae = self.sae_for(layer)
        if sae is None or sae.train is None:
            raise ValueError(f"sae.{layer} has no `train` section: layer {layer}'s SAE is not trained by this run")
        return TrainSettings(**sae.train.model_dump(include=set(TrainSettings.model_fields)))

    def steering_settings(self, layer: int, *, borrowed: bool = False) -> SteeringSettings:
        """Return the steering settings of one layer (pairs config and outputs under output_root).

        A trained layer steers through its trained SAE; `borrowed=True` gives the settings of the SAE named
        beside `train` instead (None when there is none).
        """
        sae = self.sae_for(layer)
        trained = sae is not None and sae.train is not None and not borrowed
        named = sae is not None and not trained and sae.source is not None
        return SteeringSettings(
            **self.steering.model_dump(),
            pairs_config=self.pairs_config_path(layer),
            output_root=self.steering_root,
            layer=layer,
            sae=str(self.trained_sae_dir(layer)) if trained else sae.source if named else None,
            sae_id=sae.sae_id if named else None,
            sae_dir=sae.local_dir if named else None,
            sae_cfg_from=sae.cfg_from if named else None,
            paths_relative_to="config",
        )

    def evaluate_settings(self) -> EvaluateSettings:
        """Return the evaluation settings; raise when evaluation is off."""
        if self.evaluate is None:
            raise ValueError("the run config has `evaluate: null`; add an evaluate section to evaluate the vectors")
        return EvaluateSettings(**self.evaluate.model_dump(exclude={"expert_layers"}))

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


def run_overwrite_problem(config: RunConfig) -> str | None:
    """Return the line refusing an output of the run (`output_root`, `dataset.root`) that is, contains or lies
    inside one of its inputs (`storage.overwrites`), else None."""
    inputs = {"sources.folders": config.sources.folders if config.sources is not None else None,
              "dataset.existing": config.dataset.existing, "model.checkpoint": config.model.checkpoint,
              "model.tokenizer": config.model.tokenizer, "model.norm_stats": config.model.norm_stats,
              "rollout.api_key_file": config.rollout.api_key_file if config.rollout is not None else None}
    inputs |= {f"sae.{layer}.{key}": getattr(entry, key) for layer, entry in config.sae.items() if entry is not None
               for key in ("path", "local_dir")}
    return overwrite_problem({"output_root": config.output_root, "dataset.root": config.dataset.root}, inputs,
                             of="the run")
