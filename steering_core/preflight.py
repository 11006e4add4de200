"""Checks before a run's first step: every input it will need, read cheaply, all problems at once.

A whole run takes GPU hours; a bad checkpoint path, a pickled SAE, an SAE of another width or a NaN
weight must not wait for phase 1 and capture to finish before it is reported. `run_problems` reads
headers, attributes and configs, the demos' float datasets, the checkpoint tensors the run needs (in
chunks, checking each is finite) and the SAEs (loaded on the CPU once); it creates nothing and returns
one line per problem, each naming the file or setting and what was expected.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterator
from pathlib import Path

from steering_core.capture.settings import check_model_inputs
from steering_core.capture.shards import ACTION_TOKEN_TYPES
from steering_core.config import RunConfig
from steering_core.data.dataset import resolve_task
from steering_core.data.dataset_checks import check_dataset
from steering_core.data.filtering import DEMO_FILE_GLOB, select_files
from steering_core.data.libero import validate_file
from steering_core.devices import resolve_device
from steering_core.pi05.checkpoint import (
    check_finite,
    check_prefix_layout,
    expert_arch_from_checkpoint,
    expert_tensor_shapes,
    prefix_tensor_shapes,
)
from steering_core.pi05.tokenizer import open_encoder
from steering_core.remote.filesystems import check_writable
from steering_core.storage.fileio import check_output_dir
from steering_core.storage.mirrors import url_of
from steering_core.vectors.directions import check_methods, load_steering_sae

logger = logging.getLogger(__name__)

INPUT_ERRORS = (ValueError, OSError)  # what a bad input raises in the library (FileNotFoundError is an OSError)


class PreflightError(ValueError):
    """Every problem found before a run, one line each (`problems`); str() joins them on one line."""

    def __init__(self, problems: list[str]):
        self.problems = problems
        head = "found before the run started" if len(problems) == 1 else \
            f"{len(problems)} problem(s) found before the run started"
        super().__init__(f"{head}: " + " | ".join(problems))


def check_run(config: RunConfig, *, capture_device: bool = True) -> None:
    """Raise `PreflightError` listing every problem of the run's inputs; return quietly when there are none.

    `capture_device=False` skips the capture device check where capture runs elsewhere (gpu workers).
    """
    problems = run_problems(config, capture_device=capture_device)
    if problems:
        raise PreflightError(problems)
    logger.info("preflight: every input of run %s checked", config.name)


def run_problems(config: RunConfig, *, capture_device: bool = True) -> list[str]:
    """Return one line per problem found in the run's inputs and output paths (empty: ready to run)."""
    capture = config.capture_settings()
    model = _failures([
        lambda: check_prefix_layout(capture.model.resolve(), capture.arch, max(capture.layers)),
        lambda: open_encoder(capture.model.require_tokenizer()),  # named even when the checkpoint fails first
        lambda: check_model_inputs(capture),
    ])
    if config.expert_layers and not model:  # the decision capture reads the whole policy: checked when the rest is fine
        model = _failures([lambda: check_model_inputs(config.decision_capture_settings())])
    layout_ok = not model  # the model inputs check out: model.arch is the checkpoint's, its width the SAEs' d_in
    if layout_ok:  # and every value the run will read must be finite
        model = _failures([lambda: _check_checkpoint_finite(config)])
    checks: list[Callable[[], object]] = [
        *[(lambda layer=layer: _check_sae(config, layer, check_width=layout_ok)) for layer in config.layers
          if config.sae_for(layer) is not None],
        *[(lambda layer=layer: _check_methods(config, layer, check_width=layout_ok)) for layer in config.layers],
        lambda: _check_device("steering.device", config.steering.device),
    ]
    if capture_device:  # the devices of the steps a fleet runs on its gpu and sim workers
        checks.append(lambda: _check_device("capture.device", config.capture_settings().run_device))
        checks += [(lambda layer=layer: _check_device(f"sae.{layer}.train.device", config.train_settings(layer).device))
                   for layer in config.trained_layers]
        if config.evaluate is not None:
            checks.append(lambda: _check_device("evaluate.device", config.evaluate.device))
    problems = _token_type_problems(config) + _source_problems(config) + _output_problems(config)
    rollout = rollout_input_problems(config, check_device=capture_device)
    return list(dict.fromkeys(problems + model + _failures(checks) + rollout))


def _check_device(setting: str, device: str | None) -> None:
    """Raise naming `setting` unless its device exists on this machine (`resolve_device`)."""
    try:
        resolve_device(device)
    except ValueError as err:
        raise ValueError(f"{setting}: {err}") from None


def _check_checkpoint_finite(config: RunConfig) -> None:
    """Raise naming the tensor if a checkpoint tensor the run reads holds NaN or Inf (the prefix up to the deepest
    layer; the whole prefix and the action expert when the decision rows are captured)."""
    capture = config.capture_settings()
    checkpoint = capture.model.resolve()
    if not config.expert_layers:
        check_finite(checkpoint, prefix_tensor_shapes(capture.arch, max(capture.layers)))
        return
    expert = expert_arch_from_checkpoint(checkpoint, capture.arch)
    check_finite(checkpoint, prefix_tensor_shapes(capture.arch, capture.arch.depth - 1) | expert_tensor_shapes(expert))


def _check_sae(config: RunConfig, layer: int, *, check_width: bool) -> None:
    """Load the layer's SAE on the CPU (its files, config and finite weights); with `check_width` (the checkpoint
    matches model.arch, so the arch's width is the model's), check that the SAE reads that width. A trained layer's
    SAE does not exist yet: the borrowed one it is judged against is checked."""
    settings = config.steering_settings(layer, borrowed=layer in config.trained_layers)
    sae = load_steering_sae(settings.model_copy(update={"device": "cpu"}))
    width = config.model.arch.width
    if check_width and sae is not None and sae.cfg.d_in != width:
        raise ValueError(f"{sae.cfg.source}: SAE of layer {layer} has d_in {sae.cfg.d_in}, but the model's residual "
                         f"width (model.arch.width) is {width}; pass the SAE trained on this model's layer {layer}")


def _check_methods(config: RunConfig, layer: int, *, check_width: bool) -> None:
    """Raise for a layer's steering methods that cannot run (`check_methods`); supplied files are read only when
    the checkpoint matches model.arch (its width is then the layer's)."""
    settings = config.steering_settings(layer)
    names = settings.method_list(config.sae_for(layer) is not None)
    if check_width and "file" in names:
        check_methods(settings, [pair.name for pair in config.pairs], config.model.arch.width, True)


def rollout_input_problems(config: RunConfig, *, check_device: bool = True) -> list[str]:
    """Return the problems of the rollout section: its device (unless `check_device` is False: the rollouts run on
    other machines), its scene assets, each pair's LIBERO tasks and their initial states, the server key."""
    if config.rollout is None:
        return []
    device = _failures([lambda: _check_device("rollout.device", config.rollout.device)]) if check_device else []
    from steering_core.rollout import libero_env
    from steering_core.rollout.assets import resolve_assets
    from steering_core.rollout.run import initial_states
    from steering_core.serve.auth import read_api_key

    assets = _failures([lambda: libero_env.prepare_libero(resolve_assets(config.rollout.libero_assets))])
    if assets:
        return device + assets
    wanted = config.rollout.settings().init_states
    tasks = [(lambda task=task: initial_states(task, wanted)) for pair in config.rollout.pairs.values()
             for task in (pair.positive, pair.negative)]
    return device + _failures([*tasks, lambda: read_api_key(config.rollout.api_key_file)])


def _failures(checks: list[Callable[[], object]]) -> list[str]:
    """Return the one-line message of every check that raises a bad-input error."""
    problems = []
    for check in checks:
        try:
            check()
        except INPUT_ERRORS as err:
            problems.append(one_line(err))
    return problems


def _token_type_problems(config: RunConfig) -> list[str]:
    """Return a problem when the main capture would feed action-expert rows to the SAE and steering phase."""
    token_type = config.capture.token_type
    if token_type not in ACTION_TOKEN_TYPES:
        return []
    return [f"capture.token_type: {token_type!r} captures action-expert rows, but the run's SAE and steering phase "
            "reads language-model rows (instructions, prompt or last); keep a prompt token type and set "
            "evaluate.expert_layers to capture and evaluate the action expert's decision rows"]


def _source_problems(config: RunConfig) -> list[str]:
    """Return the problems of the demo sources: missing folders, tasks matching no file, unreadable selected files."""
    if config.sources is None:
        return _dataset_problems(config)
    problems = []
    try:
        chosen, readable = select_files(config.sources.folders, config.filtered_dir, config.filter_settings())
    except INPUT_ERRORS as err:
        problems.append(one_line(err))
        chosen, readable = [], {}
    for folder in config.sources.folders:  # an unreadable file may be the one a task was meant to match
        for path in sorted(Path(folder).glob(DEMO_FILE_GLOB)) if Path(folder).is_dir() else []:
            if path not in readable:
                chosen.append(path)
    for path in dict.fromkeys(chosen):  # the files conversion will read: their demos' datasets, not only attributes
        try:
            validate_file(path)
        except INPUT_ERRORS as err:
            problems.append(one_line(err))
    return problems


def _dataset_problems(config: RunConfig) -> list[str]:
    """Return the problems of an existing dataset: unreadable metadata, missing data files, pair tasks it lacks."""
    try:
        meta = check_dataset(config.dataset_root)
    except INPUT_ERRORS as err:
        return [one_line(err)]
    problems = []
    for text in dict.fromkeys(text for pair in config.pairs for text in (pair.positive, pair.negative)):
        try:
            resolve_task(meta, text)
        except ValueError as err:
            problems.append(one_line(err))
    return problems


def _output_problems(config: RunConfig) -> list[str]:
    """Return one problem per culprit (a file where a folder goes, a read-only folder) among the output folders."""
    problems: dict[str, str] = {}
    if (url := url_of(config.output_root)) is not None:  # a bucket root: this machine must be able to write there
        try:
            check_writable(url)
        except ValueError as err:
            problems[url] = one_line(err)
    for path, what in _output_dirs(config):
        try:
            check_output_dir(path, what)
        except ValueError as err:
            problems.setdefault(str(err).split(":")[0], one_line(err))  # the culprit path leads the message
    return list(problems.values())


def _output_dirs(config: RunConfig) -> Iterator[tuple[Path, str]]:
    """Yield every folder the run writes into, with what it is for."""
    yield config.output_root, "output root"
    if config.converts:  # an existing dataset is read, never written: it may well be read-only
        yield config.filtered_dir, "filtered demos folder"
        yield config.dataset_root, "dataset folder"
    yield config.run_dir, "residual run folder"
    if config.expert_layers:
        yield config.decision_run_dir, "decision run folder"
    for pair in config.pairs:
        yield config.manifest_path(pair).parent, "manifests folder"
        yield config.slices_dir(pair), "slices folder"
        if config.expert_layers:
            yield config.decision_slices_dir(pair), "decision slices folder"
    for layer in config.layers:
        yield config.layer_path(layer), "steering folder"


def one_line(err: BaseException, items: int = 3) -> str:
    """Return an error's message on one line: listed items joined by '; ', beyond `items` only counted.

    A `FileNotFoundError` from `open()` names the file only in `filename`; it is put first.
    """
    text = str(err)
    if isinstance(err, OSError) and err.filename and str(err.filename) not in text:
        text = f"{err.filename}: {err.strerror or text}"
    lines = [line.strip().removeprefix("- ").strip() for line in text.splitlines() if line.strip()] or [
        type(err).__name__]
    head, listed = lines[0], lines[1:]
    if len(listed) > items + 1:  # keep the first items and the closing advice
        listed = [*listed[:items], f"... {len(listed) - items - 1} more", listed[-1]]
    return " ".join([head, "; ".join(listed)]) if listed else head
