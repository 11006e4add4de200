"""LIBERO hdf5 demo files: schema, validation on open, instruction lookup, demo reading.

The schema is the one LIBERO's `scripts/create_dataset.py` wrote for the released
files (docs/PI05_SPEC.md section 7)::

    data/                      attrs: problem_info (JSON), bddl_file_content, env_args, num_demos, total
    data/demo_<k>/             attrs: num_samples, model_file, init_state
        obs/agentview_rgb      (T, H, W, 3) uint8   third-person camera, raw render (upside down)
        obs/eye_in_hand_rgb    (T, H, W, 3) uint8   wrist camera, raw render (upside down)
        obs/ee_pos             (T, 3) float         end-effector position
        obs/ee_ori             (T, 3) float         end-effector orientation, axis-angle
        obs/ee_states          (T, 6) float         ee_pos and ee_ori concatenated
        obs/gripper_states     (T, 2) float         gripper finger joint positions
        obs/joint_states       (T, 7) float         arm joint positions
        actions                (T, 7) float         delta position, delta rotation, gripper
        states                 (T, S) float         flattened MuJoCo state, S depends on the scene
        robot_states           (T, 9) float         gripper qpos, eef position, eef quaternion
        rewards, dones         (T,)   uint8         0 except 1 at the last step

Every reader validates the whole file's layout on open (metadata, and the float datasets' values:
NaN or Inf is refused; images are not read), collects every problem and raises one `ValueError`
naming file, demo, dataset, found and expected.
"""

from __future__ import annotations

import contextlib
import json
import logging
import re
from collections import Counter
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import h5py
import numpy as np

from steering_core.storage.finite import non_finite

logger = logging.getLogger(__name__)

DATA_GROUP = "data"
DEMO_KEY_PATTERN = re.compile(r"^demo_(\d+)$")
DEMO_KEY = "demo_{index}"
FILE_SUFFIX = "_demo.hdf5"
FILE_NAME = "{task_name}" + FILE_SUFFIX  # e.g. KITCHEN_SCENE1_open_the_top_drawer_of_the_cabinet_demo.hdf5

# dataset path inside a demo group -> (dtype kind, trailing shape). Kinds: "image" = uint8
# (H, W, 3); "float" = any float width (LIBERO wrote float64, other writers float32);
# "flag" = integer or bool. None in a trailing shape means "any positive size".
DEMO_SCHEMA: dict[str, tuple[str, tuple[int | None, ...]]] = {
    "obs/agentview_rgb": ("image", (None, None, 3)),
    "obs/eye_in_hand_rgb": ("image", (None, None, 3)),
    "obs/ee_pos": ("float", (3,)),
    "obs/ee_ori": ("float", (3,)),
    "obs/ee_states": ("float", (6,)),
    "obs/gripper_states": ("float", (2,)),
    "obs/joint_states": ("float", (7,)),
    "actions": ("float", (7,)),
    "states": ("float", (None,)),
    "robot_states": ("float", (9,)),
    "rewards": ("flag", ()),
    "dones": ("flag", ()),
}
_KIND_TEXT = {"image": "uint8", "float": "float", "flag": "uint8"}
# Bounds on declared shapes, checked before any data is read: a small file may declare a huge dataset. LIBERO's
# demos run at most a few hundred steps at 128-256 px; its flattened MuJoCo state has about a hundred values.
MAX_DEMO_STEPS = 100_000
MAX_IMAGE_SIDE = 4096
MIN_IMAGE_SIDE = 8  # the smallest image the converter resizes (its --image-size bound)
MAX_STATE_WIDTH = 10_000
# LIBERO's floats are metres, radians, joint velocities and actions in [-1, 1]; far beyond that a value is corrupt,
# and past ~1e19 its square (statistics) overflows float32 (1e300 is finite in float64, Inf in float32).
MAX_ABS_VALUE = 1e9

InstructionSource = Literal["problem_info", "bddl", "filename"]
_BDDL_LANGUAGE = re.compile(r"\(:language\s+([^()]*?)\s*\)", re.DOTALL)
_SCENE_PREFIX = re.compile(r"^.*?SCENE\d+_")  # KITCHEN_SCENE10_, LIVING_ROOM_SCENE2_, STUDY_SCENE1_
_FIX = "re-export the file with LIBERO's scripts/create_dataset.py, or remove it from the input folder"


@dataclass(frozen=True)
class LiberoDemo:
    """One demonstration: every array has the same first dimension T (steps at 20 Hz)."""

    key: str                      # "demo_<k>"
    agentview_rgb: np.ndarray     # (T, H, W, 3) uint8, raw render orientation
    eye_in_hand_rgb: np.ndarray   # (T, H, W, 3) uint8, raw render orientation
    ee_pos: np.ndarray            # (T, 3) float64
    ee_ori: np.ndarray            # (T, 3) float64 axis-angle
    ee_states: np.ndarray         # (T, 6) float64
    gripper_states: np.ndarray    # (T, 2) float64
    joint_states: np.ndarray      # (T, 7) float64
    actions: np.ndarray           # (T, 7) float64
    states: np.ndarray            # (T, S) float64
    robot_states: np.ndarray      # (T, 9) float64
    rewards: np.ndarray           # (T,) uint8
    dones: np.ndarray             # (T,) uint8

    @property
    def num_steps(self) -> int:
        """Return T, the number of steps."""
        return int(self.actions.shape[0])

    def state8(self) -> np.ndarray:
        """Return the openpi LIBERO state (T, 8) float32: ee_pos (3), ee_ori axis-angle (3), gripper (2)."""
        return np.concatenate([self.ee_pos, self.ee_ori, self.gripper_states], axis=1).astype(np.float32)


@dataclass(frozen=True)
class LiberoFileInfo:
    """What validation learned about one file, without reading array data."""

    path: Path
    instruction: str
    instruction_source: InstructionSource
    demo_lengths: dict[str, int]  # demo key -> T, in numeric key order

    @property
    def demo_keys(self) -> list[str]:
        """Return the demo keys in numeric order (demo_9 before demo_10)."""
        return list(self.demo_lengths)

    @property
    def num_demos(self) -> int:
        """Return the number of demos in the file."""
        return len(self.demo_lengths)


def instruction_from_filename(path: str | Path) -> str:
    """Return the task text encoded in a LIBERO file name.

    `KITCHEN_SCENE10_close_the_top_drawer_of_the_cabinet_demo.hdf5` and
    `LIVING_ROOM_SCENE2_pick_up_the_milk_demo.hdf5` lose everything through `SCENE<n>_`;
    names without a scene prefix (the spatial suite) keep all their words.
    """
    stem = Path(path).name
    for suffix in (FILE_SUFFIX, ".hdf5"):
        if stem.endswith(suffix):
            stem = stem[: -len(suffix)]
            break
    return _clean_text(_SCENE_PREFIX.sub("", stem, count=1).replace("_", " "))


def task_file_name(instruction: str, scene: str) -> str:
    """Return the LIBERO file name of a task, e.g. `KITCHEN_SCENE3_turn_on_the_stove_demo.hdf5`."""
    return FILE_NAME.format(task_name=f"{scene}_{'_'.join(instruction.split())}")


def demo_sort_key(key: str) -> int:
    """Return the numeric index of a `demo_<k>` key (so demo_10 sorts after demo_9)."""
    match = DEMO_KEY_PATTERN.match(key)
    if match is None:
        raise ValueError(f"demo key {key!r} does not look like demo_<k>")
    return int(match.group(1))


def read_instruction(path: str | Path) -> str:
    """Return the task instruction of a LIBERO file (see `read_instruction_with_source`)."""
    return read_instruction_with_source(path)[0]


def read_instruction_with_source(path: str | Path) -> tuple[str, InstructionSource]:
    """Return (instruction, where it came from) reading only the `data` attributes.

    Order: `problem_info.language_instruction`, then the BDDL `(:language ...)`, then the
    file name. Malformed attributes raise `ValueError` rather than silently falling back.
    """
    path = _existing(path)
    with _open_hdf5(path) as handle:
        indirection = _indirection_problem(handle, DATA_GROUP, DATA_GROUP)
        if indirection:
            raise ValueError(_report(path, [indirection]))
        if DATA_GROUP not in handle:
            raise ValueError(f"{path}: no `{DATA_GROUP}` group; expected a LIBERO demo file; {_FIX}")
        text, source, problems = _instruction(path, handle[DATA_GROUP].attrs)
    if problems:
        raise ValueError(_report(path, problems))
    return text, source


def validate_file(path: str | Path) -> LiberoFileInfo:
    """Return the file's instruction and demo lengths; raise one ValueError listing every schema problem."""
    path = _existing(path)
    with _open_validated(path) as (_, info):
        return info


def list_demos(path: str | Path) -> list[str]:
    """Return the demo keys of a validated file in numeric order (gaps allowed)."""
    return validate_file(path).demo_keys


def read_demo(path: str | Path, key: str) -> LiberoDemo:
    """Return one demo of a validated file with all its arrays loaded."""
    (demo,) = iter_demos(path, [key])  # consuming the generator closes the file
    return demo


def iter_demos(path: str | Path, keys: Sequence[str] | None = None) -> Iterator[LiberoDemo]:
    """Yield the demos `keys` (default: all, in numeric order) of a validated file, opening it once."""
    path = _existing(path)
    with _open_validated(path) as (handle, info):
        wanted = info.demo_keys if keys is None else list(keys)
        missing = [key for key in wanted if key not in info.demo_lengths]
        if missing:
            raise ValueError(f"{path}: no demo(s) {missing}; available: {_preview(info.demo_keys)}")
        for key in wanted:
            yield _load_demo(handle[DATA_GROUP][key], key)


# ----------------------------------------------------------------------------- internals


def _existing(path: str | Path) -> Path:
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: LIBERO demo file not found")
    return path


@contextlib.contextmanager
def _open_hdf5(path: Path) -> Iterator[h5py.File]:
    try:
        handle = h5py.File(path, "r")
    except OSError as err:
        raise ValueError(f"{path}: not a readable HDF5 file ({err}); {_FIX}") from None
    with handle:
        yield handle


@contextlib.contextmanager
def _open_validated(path: Path) -> Iterator[tuple[h5py.File, LiberoFileInfo]]:
    with _open_hdf5(path) as handle:
        problems: list[str] = []
        indirection = _indirection_problem(handle, DATA_GROUP, DATA_GROUP)
        if indirection:
            raise ValueError(_report(path, [indirection]))
        if DATA_GROUP not in handle or not isinstance(handle[DATA_GROUP], h5py.Group):
            raise ValueError(_report(path, [f"no `{DATA_GROUP}` group (found top-level keys {sorted(handle)})"]))
        data = handle[DATA_GROUP]
        instruction, source, attr_problems = _instruction(path, data.attrs)
        problems += attr_problems
        demo_keys = sorted((k for k in data if DEMO_KEY_PATTERN.match(k)), key=demo_sort_key)
        if not demo_keys:
            problems.append(f"`data` has no demo_<k> groups (found {_preview(sorted(data))})")
        stray = sorted(k for k in data if k not in demo_keys or k != DEMO_KEY.format(index=demo_sort_key(k)))
        if stray and demo_keys:  # skipped silently, a demo would vanish (demo_x, demo_-5, demo_07 beside demo_7)
            problems.append(f"`data` holds {_preview(stray)}, expected only demo_<k> groups (k = 0, 1, ...)")
        lengths: dict[str, int] = {}
        for key in demo_keys:
            indirection = _indirection_problem(data, key, f"data/{key}")
            length, demo_problems = (0, [indirection]) if indirection else _check_demo(data[key], key)
            problems += demo_problems
            lengths[key] = length
        if problems:
            raise ValueError(_report(path, problems))
        yield handle, LiberoFileInfo(path, instruction, source, lengths)


def _check_demo(group: h5py.Group | h5py.Dataset, key: str) -> tuple[int, list[str]]:
    """Return (T, problems) for one demo group, checking names, dtypes, shapes and step counts."""
    if not isinstance(group, h5py.Group):
        return 0, [f"data/{key} is a dataset, expected a group"]
    problems: list[str] = []
    first_dims: dict[str, int] = {}
    for name, (kind, trailing) in DEMO_SCHEMA.items():
        where = f"data/{key}/{name}"
        indirection = _indirection_problem(group, name, where)
        if indirection:
            problems.append(indirection)
            continue
        item = group.get(name)
        if item is None:
            problems.append(f"{where} is missing")
            continue
        if not isinstance(item, h5py.Dataset):
            problems.append(f"{where} is a group, expected a dataset")
            continue
        shape, dtype = item.shape, item.dtype
        shape_ok = len(shape) == 1 + len(trailing) and all(
            (want is None and got > 0) or got == want for got, want in zip(shape[1:], trailing)
        )
        too_large = _shape_bound_problem(kind, shape, where)
        if too_large:
            problems.append(too_large)
            continue
        if not shape_ok or not _dtype_ok(kind, dtype):
            problems.append(f"{where} is {shape} {dtype}, expected {_shape_text(trailing)} {_KIND_TEXT[kind]}")
        elif kind == "float":  # states, actions and the like: small next to the images, read whole
            problems += _finite_problems(item, key, name)
        if len(shape) >= 1:
            first_dims[name] = shape[0]
    if not first_dims:
        return 0, problems
    steps, _ = Counter(first_dims.values()).most_common(1)[0]
    for name, length in first_dims.items():
        if length != steps:
            problems.append(f"data/{key}/{name} has {length} steps, expected {steps} like the demo's other datasets")
    if steps == 0:
        problems.append(f"data/{key} has 0 steps, expected at least 1")
    num_samples = group.attrs.get("num_samples")
    if num_samples is not None and int(np.asarray(num_samples)) != steps:
        found = int(np.asarray(num_samples))
        problems.append(f"data/{key} attribute num_samples is {found}, expected {steps} (the datasets' T)")
    return steps, problems


def _indirection_problem(parent: h5py.Group, name: str, where: str) -> str | None:
    """Return the problem of `name` reading anything but this file's own bytes, else None: a LIBERO demo file holds
    its own data. Refused: a soft or external link on its path (a loop, or a file elsewhere), and a dataset whose
    values lie elsewhere (external raw storage, or a virtual dataset, whose missing sources read as fill values)."""
    parts = name.split("/")
    for depth in range(1, len(parts) + 1):
        step = "/".join(parts[:depth])
        try:
            link = parent.get(step, getlink=True)
        except (KeyError, RuntimeError, OSError) as err:  # h5py's errors resolving a broken path
            return f"{where}: cannot be resolved ({err}), expected the data itself"
        if isinstance(link, h5py.SoftLink):
            return f"{where} goes through a soft link to {link.path!r}, expected the data itself"
        if isinstance(link, h5py.ExternalLink):
            return f"{where} goes through an external link to {link.filename}:{link.path}, expected the data itself"
        if link is None:
            return None
    item = parent[name]
    if not isinstance(item, h5py.Dataset):
        return None
    if item.external:
        files = sorted({file for file, _, _ in item.external})
        return f"{where} keeps its values in other files {files} (external storage), expected the data itself"
    if item.is_virtual:
        sources = sorted({f"{source.file_name}:{source.dset_name}" for source in item.virtual_sources()})
        return f"{where} is a virtual dataset mapping {sources}, expected the data itself"
    return None


def _shape_bound_problem(kind: str, shape: tuple[int, ...], where: str) -> str | None:
    """Return the problem of a declared shape beyond the bounds (steps, image side, state width), else None."""
    bounds = [("steps", MAX_DEMO_STEPS)] + {"image": [("height", MAX_IMAGE_SIDE), ("width", MAX_IMAGE_SIDE)],
                                           "float": [("width", MAX_STATE_WIDTH)]}.get(kind, [])
    over = [f"{name} {size} > {bound}" for (name, bound), size in zip(bounds, shape) if size > bound]
    if kind == "image":  # an image the converter cannot orient and resize: LIBERO renders 128x128
        over += [f"{name} {size} < {MIN_IMAGE_SIDE}" for name, size in zip(("height", "width"), shape[1:3])
                 if size < MIN_IMAGE_SIDE]
    return f"{where} declares shape {shape}: {', '.join(over)}; not a LIBERO demo" if over else None


def _finite_problems(item: h5py.Dataset, key: str, name: str) -> list[str]:
    """Return the problem of a float dataset holding NaN or Inf (`non_finite`'s message) or values beyond
    `MAX_ABS_VALUE`, else none."""
    values = item[()]
    problem = non_finite(values, f"data/{key}/{name}")
    if problem is None and values.size and (largest := float(np.abs(values).max())) > MAX_ABS_VALUE:
        problem = f"data/{key}/{name} holds {largest:g}, expected magnitudes up to {MAX_ABS_VALUE:g}"
    return [] if problem is None else [problem]


def _shape_text(trailing: tuple[int | None, ...]) -> str:
    """Return the expected shape as text, e.g. `(T, 3)`, `(T, *, *, 3)` or `(T,)`."""
    dims = ["T", *("*" if d is None else str(d) for d in trailing)]
    return f"({dims[0]},)" if len(dims) == 1 else f"({', '.join(dims)})"


def _dtype_ok(kind: str, dtype: np.dtype) -> bool:
    if kind == "image":
        return dtype == np.uint8
    if kind == "float":
        return dtype.kind == "f"
    return dtype.kind in "uib"


def _instruction(path: Path, attrs: h5py.AttributeManager) -> tuple[str, InstructionSource, list[str]]:
    """Return (text, source, problems) following problem_info -> BDDL -> file name."""
    problems: list[str] = []
    raw = attrs.get("problem_info")
    if raw is not None:
        try:
            info = json.loads(_as_str(raw))
        except (json.JSONDecodeError, UnicodeDecodeError) as err:
            problems.append(f"data attribute problem_info is not valid JSON ({getattr(err, 'msg', None) or err}), "
                            "expected a JSON object in UTF-8 text")
        else:
            value = info.get("language_instruction") if isinstance(info, dict) else None
            if isinstance(value, list):
                # LIBERO's reader joins list-valued instructions; joining words with spaces keeps them apart.
                value = " ".join(str(part) for part in value)
            if isinstance(value, str) and _clean_text(value):
                return _clean_text(value), "problem_info", problems
            logger.debug("%s: problem_info has no usable language_instruction; trying the BDDL", path.name)
    bddl = attrs.get("bddl_file_content")
    if bddl is not None:
        match = _BDDL_LANGUAGE.search(_as_str(bddl, errors="replace"))  # only its language line is read
        if match and _clean_text(match.group(1)):
            return _clean_text(match.group(1)), "bddl", problems
    logger.debug("%s: no instruction attribute; using the file name", path.name)
    return instruction_from_filename(path), "filename", problems


def _clean_text(text: str) -> str:
    """Return text with surrounding quotes removed (as LIBERO's reader does) and whitespace collapsed."""
    return " ".join(text.strip().strip('"').split())


def _as_str(value: object, errors: str = "strict") -> str:
    if isinstance(value, bytes):
        return value.decode("utf-8", errors)
    if isinstance(value, np.ndarray) and value.shape == ():
        return _as_str(value.item(), errors)
    return str(value)


def _load_demo(group: h5py.Group, key: str) -> LiberoDemo:
    arrays = {Path(name).name: np.asarray(group[name][()]) for name in DEMO_SCHEMA}
    return LiberoDemo(key=key, **arrays)


def _report(path: Path, problems: list[str]) -> str:
    """Return every problem of a file on one line, naming the file first and the fix last."""
    return f"{path}: {len(problems)} problem(s) with the LIBERO demo schema: {'; '.join(problems)}; fix: {_FIX}"


def _preview(items: list[str], limit: int = 8) -> str:
    shown = ", ".join(items[:limit])
    return f"[{shown}{', ...' if len(items) > limit else ''}]"
