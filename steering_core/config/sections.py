"""The run config's sections: where demos come from, the dataset, pairs, model, SAEs, orchestration, and
each step's own settings minus the fields the run config supplies itself (`SUPPLIED`)."""

from __future__ import annotations

import copy
import os
import re
from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import (
    AfterValidator,
    AliasChoices,
    BeforeValidator,
    Field,
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
from steering_core.layout import check_name
from steering_core.pairs import same_text
from steering_core.pi05.spec import ModelSpec
from steering_core.remote.publish import pull
from steering_core.rollout.settings import RolloutPair, RolloutSettings
from steering_core.sae.training.settings import TrainSettings
from steering_core.storage.mirrors import is_url, mount
from steering_core.storage.schema import StrictModel
from steering_core.vectors.directions import SteeringSettings

SAFE_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]*$")
MAX_NAME_CHARS = 100  # a name becomes a path component with suffixes added (the file system allows 255 bytes)
# Step settings the run config supplies itself, and where to set them instead.
SUPPLIED = {
    "capture": {"model": "model", "layers": "layers"},
    "slicing": {"layers": "layers", "token_type": "capture.token_type", "holdout_episodes": "evaluate.holdout_fraction"},
    "steering": {"pairs_config": "pairs", "output_root": "output_root", "layer": "layers", "sae": "sae.<layer>",
                 "sae_id": "sae.<layer>.sae_id", "sae_dir": "sae.<layer>.local_dir",
                 "sae_cfg_from": "sae.<layer>.cfg_from", "paths_relative_to": "output_root"},
}

# Former key names still read, section -> former -> current; given beside the current one, a former name is refused.
FORMER_NAMES = {"orchestration": {"capture": "mode"}}
# Keys that moved to another section, section -> key -> where it is set now (named when an old config gives one).
MOVED = {"capture": {"checkpoint_path": "model.checkpoint", "tokenizer_path": "model.tokenizer",
                     "norm_stats_path": "model.norm_stats", "norm_stats_asset_id": "model.asset_id",
                     "arch": "model.arch", "prompt_format": "model.prompt_format",
                     "max_token_len": "model.max_token_len", "action_horizon": "model.action_horizon"},
         "evaluate": {"top_k": "steering.top_k"}, "rollout": {"direction": "rollout.methods"}}


def _resolve_path(value: Path, info: ValidationInfo) -> Path:
    """Return `value` made absolute against the config file's folder (validation context `base_dir`)."""
    value = value.expanduser()
    base = (info.context or {}).get("base_dir")
    return value if value.is_absolute() or base is None else Path(base) / value


def _mounted(role: str) -> Any:
    """Return a validator mounting a URL (`s3://...`, `gs://...`) as its local mirror folder (`storage.mirrors`);
    an input root is pulled into it."""
    def validate(value: Any) -> Any:
        if not is_url(value):
            return value
        path = mount(os.fspath(value), role)
        if role == "input":
            try:
                pull(path)  # what the run reads, fetched once per machine (again only when an object changed)
            except (OSError, RuntimeError) as err:  # s3fs and gcsfs report unreachable or denied stores so
                raise ValueError(f"{os.fspath(value)}: cannot be read from this machine ({type(err).__name__}: "
                                 f"{err}); check the URL and the AWS_* / GOOGLE_APPLICATION_CREDENTIALS settings") from None
        return path
    return validate


ConfigPath = Annotated[Path, BeforeValidator(_mounted("input")), AfterValidator(_resolve_path)]  # read by the run
OutputPath = Annotated[Path, BeforeValidator(_mounted("output")), AfterValidator(_resolve_path)]  # written by it


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
_ConvertOptions = options_model(ConvertSettings, (), "_ConvertOptions", root=(OutputPath | None, None))
CaptureSection = options_model(CaptureSettings, tuple(SUPPLIED["capture"]), "CaptureSection")
SliceSection = options_model(SliceSettings, tuple(SUPPLIED["slicing"]), "SliceSection")
SteeringSection = options_model(SteeringSettings, tuple(SUPPLIED["steering"]), "SteeringSection")


def _expert_layers(layers: tuple[int, ...]) -> tuple[int, ...]:
    """Return the expert layers sorted and without repeats; refuse negative ones."""
    if any(layer < 0 for layer in layers):
        raise ValueError(f"expert_layers {list(layers)} include a negative index; expert layers count from 0")
    return tuple(sorted(set(layers)))


# The evaluation settings plus the run-level choice of action-expert layers: capturing their `decision` rows is
# a second capture run, so the list belongs to the run config, not to each (pair, layer) evaluation.
EvaluateSection = options_model(
    EvaluateSettings, (), "EvaluateSection",
    expert_layers=(Annotated[tuple[int, ...], AfterValidator(_expert_layers)], ()),
)


class DatasetSection(_ConvertOptions):
    """The LeRobot dataset of the run: converted from `sources` (ConvertSettings fields, optional `root`
    to write it elsewhere), or an `existing` dataset folder read in place, never written into."""

    existing: ConfigPath | None = None   # a LeRobot v2.0/v2.1/v3.0 dataset root (a read-only HF cache is fine)
    repo_id: str | None = Field(None, min_length=1)  # existing: defaults to the folder's name

    @field_validator("repo_id")
    @classmethod
    def _repo_id_is_a_path(cls, repo_id: str | None) -> str | None:
        return repo_id if repo_id is None else check_name(repo_id, "repo_id", nested=True)  # libero_lerobot/<repo_id>

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
    suite: str = Field("demos", pattern=SAFE_NAME.pattern, max_length=MAX_NAME_CHARS)  # libero_filtered/<suite>/


class PairSection(StrictModel):
    """One concept pair: two task texts of the dataset, contrasted by a manifest."""

    name: str = Field(pattern=SAFE_NAME.pattern, max_length=MAX_NAME_CHARS)  # folder and file names: manifests/<name>.json
    positive: str = Field(min_length=1)            # task text of the positive concept (task A)
    negative: str = Field(min_length=1)            # task text of the negative concept (task B)
    rename: dict[str, str] = {}                    # task text -> concept name, as in the seed
    manifest: ContrastSettings = ContrastSettings()

    @model_validator(mode="after")
    def _two_tasks(self) -> PairSection:
        if same_text(self.positive, self.negative):
            raise ValueError(f"positive and negative are both {self.positive!r}; a pair needs two different tasks")
        concepts = self.concept(self.positive), self.concept(self.negative)
        if same_text(*concepts):
            raise ValueError(f"rename gives positive {self.positive!r} and negative {self.negative!r} one concept "
                             f"{concepts[0]!r}; a pair needs two different concept names")
        return self

    def concept(self, task: str) -> str:
        """Return the concept name of one of the pair's task texts (after `rename`)."""
        return self.rename.get(task, task)


class ModelSection(ModelSpec):
    """The run's pi0.5 model (`ModelSpec`), its paths relative to the config file; the tokenizer is required."""

    checkpoint: ConfigPath
    tokenizer: ConfigPath
    norm_stats: ConfigPath | None = None


class SaeTrainSection(TrainSettings):
    """Train this layer's SAE on the run's own residuals, judge it, and steer through it."""

    judge_frames: int = Field(8, ge=1, le=256)  # held-out frames whose actions judge the reconstruction
    heldout_fraction: float = Field(0.1, gt=0, lt=1)  # episodes kept out of training when no pair holds any out
    feature_examples: int = Field(8, ge=1, le=64)  # top-activating frames per latent on the feature page


class SaeSection(StrictModel):
    """One layer's SAE: a release of the registry (+ sae id), a path (folder or state dict), or `train`.

    With `train`, the SAE trained on this run's residuals steers; a `release` or `path` beside it names the
    borrowed SAE it is judged against.
    """

    release: str | None = None
    sae_id: str | None = None              # default blocks.<layer>.hook_resid_post
    path: ConfigPath | None = None
    local_dir: ConfigPath | None = None    # folder of release folders, searched before the HF cache
    cfg_from: str | None = None            # state-dict SAE: folder or release whose cfg.json applies
    train: SaeTrainSection | None = None   # train on the run's residuals (saes/<run>/layerNN/)

    @model_validator(mode="after")
    def _one_source(self) -> SaeSection:
        if self.release is not None and self.path is not None:
            raise ValueError("give one of `release` (with optional `sae_id`) or `path`, not both")
        if self.release is None and self.path is None and self.train is None:
            raise ValueError("give `release` (with optional `sae_id`), `path`, or `train`")
        if self.sae_id is not None and self.release is None and self.cfg_from is None:
            raise ValueError("`sae_id` needs `release` (or `cfg_from` for a state dict)")
        return self

    @property
    def source(self) -> str | None:
        """Return what `steering_core.sae.load_sae` takes as its source (None: only trained)."""
        if self.release is not None:
            return self.release
        return None if self.path is None else str(self.path)


class OrchestrationSection(StrictModel):
    """How the Prefect flows run the steps (no effect on any output)."""

    # where the phases that can run on workers run (capture, SAE training, evaluation, rollouts): `deployment`,
    # `local` (in the parent's process) or `auto` (deployments when the parent runs from one); `capture:` is its
    # former name, still read (FORMER_NAMES)
    mode: Literal["auto", "deployment", "local"] = Field("auto", validation_alias=AliasChoices("mode", "capture"))
    capture_deployment: str = "latent-steering-capture/gpu"  # when run from one
    evaluate_deployment: str = "latent-steering-evaluate/gpu-evaluate"
    train_deployment: str = "latent-steering-train-sae/gpu-train-sae"
    rollout_deployment: str = "latent-steering-rollout/sim-rollout"
    pipeline_deployment: str = "latent-steering/pipeline"     # what a scheduled refresh starts
    shards_per_capture_run: int = Field(8, ge=1, le=100_000)  # episode groups per GPU flow run (one model load each)
    poll_seconds: float = Field(5.0, gt=0, le=3600)  # how often the parent checks its capture runs
    worker_wait_seconds: float = Field(600.0, gt=0)  # child runs still unstarted, no worker of their pool: fail
    resubmits: int = Field(2, ge=0, le=100)  # times a crashed child run (its process or machine died) is started again
    deadline_seconds: float = Field(86400.0, gt=0)  # a phase's child runs not all finished by then: cancel, fail
    # a running child silent this long while the server records the parent's own heartbeats: dead, marked Crashed
    # (flows/heartbeats.py; deployments/README.md, "When a worker or a machine dies")
    heartbeat_timeout_seconds: float = Field(300.0, ge=60)


class RolloutSection(RolloutSettings):
    """Phase 5: the rollout settings plus the LIBERO tasks of each pair rolled out (paths relative to the config)."""

    pairs: dict[str, RolloutPair] = Field(min_length=1)  # pair name -> its two LIBERO tasks
    layers: tuple[int, ...] | None = None                # None: every layer of the run
    api_key_file: ConfigPath | None = None

    def settings(self) -> RolloutSettings:
        """Return the settings every (pair, layer) shares."""
        return RolloutSettings(**self.model_dump(exclude={"pairs", "layers"}))
