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
evaluate: {holdout_fraction: 0.2, max_frames: 32}    # EvaluateSettings; null: no phase 4
# evaluate: {expert_layers: [9]}   # also capture `decision` rows at these action-expert layers and evaluate them
```

Sections that reuse a step's settings model take its fields minus those the run config supplies
(paths under `output_root`, `layers`, the model and SAE sections); the full settings of each step
are built by `RunConfig.*_settings()`, so the pipeline and the CLI steps always agree. Errors from
`load_run_config` name the file and the key path: `run.yaml: pairs[1].positive: field required`.

Modules: `sections` (the sections, most of them a step's settings minus what the run supplies), `run`
(`RunConfig`: the sections together, the seed's paths under `output_root`, each step's full settings),
`yaml_files` (reading and writing run.yaml, errors by key path).
"""

from steering_core.config.run import PAIRS_CONFIG_FILE, RunConfig
from steering_core.config.sections import (
    CaptureSection,
    ConfigPath,
    DatasetSection,
    EvaluateSection,
    ModelSection,
    OrchestrationSection,
    PairSection,
    RolloutSection,
    SaeSection,
    SaeTrainSection,
    SliceSection,
    SourcesSection,
    SteeringSection,
)
from steering_core.config.yaml_files import (
    CONFIG_FILE,
    claim_config_file,
    format_errors,
    load_run_config,
    share_run_config,
    write_run_config,
)

__all__ = [
    "CONFIG_FILE", "PAIRS_CONFIG_FILE", "CaptureSection", "ConfigPath", "DatasetSection", "EvaluateSection",
    "ModelSection", "OrchestrationSection", "PairSection", "RolloutSection", "RunConfig", "SaeSection", "SaeTrainSection",
    "SliceSection",
    "SourcesSection", "SteeringSection", "claim_config_file", "format_errors", "load_run_config", "share_run_config",
    "write_run_config",
]
