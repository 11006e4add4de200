"""run.yaml on disk: read and validated with every problem as `<file>: <key path>: <message>`, or written back."""

from __future__ import annotations

import hashlib
import os
from collections.abc import Hashable
from pathlib import Path
from typing import Any

import yaml
from pydantic import ValidationError

from steering_core.config.run import RunConfig
from steering_core.config.sections import FORMER_NAMES, MOVED, SUPPLIED
from steering_core.remote.filesystems import object_path, temporary_copy
from steering_core.storage.fileio import atomic_path, read_text
from steering_core.storage.mirrors import is_url, portable, url_of
from steering_core.storage.schema import error_message

CONFIG_FILE = "run.yaml"  # name used when a run config is written next to its outputs


def load_run_config(path: str | os.PathLike) -> RunConfig:
    """Return the validated run config of a YAML file; relative paths resolve against its folder.

    Raises FileNotFoundError when the file is missing, ValueError listing every problem as
    `<file>: <key path>: <message>` otherwise.
    """
    if is_url(path):  # a config handed to workers on other machines through the bucket
        try:
            path = temporary_copy(os.fspath(path))
        except FileNotFoundError:
            raise FileNotFoundError(f"{os.fspath(path)}: run config not found in the bucket") from None
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: run config not found; pass --config with a YAML file (see README)")
    text = read_text(path, "a run config (YAML)")
    try:
        data = yaml.load(text, Loader=UniqueKeyLoader)  # a SafeLoader: no Python objects
    except yaml.YAMLError as err:
        mark = getattr(err, "problem_mark", None)
        where = f"line {mark.line + 1}, column {mark.column + 1}: " if mark is not None else ""
        raise ValueError(f"{path}: not valid YAML ({where}{getattr(err, 'problem', None) or err})") from None
    if not isinstance(data, dict):
        raise ValueError(f"{path}: expected a mapping of sections (sources, dataset, pairs, ...), found {type(data).__name__}")
    try:
        return RunConfig.model_validate(data, context={"base_dir": path.resolve().parent})
    except ValidationError as err:
        lines = format_errors(err, data)
        if len(lines) > MAX_ERROR_LINES:
            lines = [*lines[:MAX_ERROR_LINES], f"... and {len(lines) - MAX_ERROR_LINES:,} more problems"]
        raise ValueError("\n".join(f"{path}: {line}" for line in lines)) from None


MAX_DEPTH = 64  # mappings and lists inside each other; a run config nests 5 deep, Python's recursion stops near 300
MAX_ERROR_LINES = 20  # problems listed of an invalid config; the count of the others follows
MAX_VALUES = 100_000  # values a document's aliases add, each counted as what it repeats; a run config holds ~200


class UniqueKeyLoader(yaml.SafeLoader):
    """YAML's safe loader, refusing a mapping that names one key twice (YAML would silently keep the last), values
    nested more than `MAX_DEPTH` deep (before the recursion that builds them could exhaust Python's stack), and a
    document whose aliases add more than `MAX_VALUES` values to those written (a few hundred bytes of nested aliases
    repeat a list billions of times: counted on the composed nodes, before anything is built from them).

    Keys merged in with `<<: *alias` may be overridden: only keys written in the mapping itself are compared.
    """

    depth = 0

    def compose_document(self) -> yaml.Node | None:
        node = super().compose_document()
        sizes: dict[int, int] = {}
        if _expanded_values(node, sizes) - len(sizes) > MAX_VALUES:  # what the aliases add to the values written
            raise yaml.composer.ComposerError(None, None, f"its aliases expand to more than {MAX_VALUES:,} values "
                                              "beyond those written (each alias counts as what it repeats); a run "
                                              "config holds a few hundred: write the values out", node.start_mark)
        return node

    def compose_node(self, parent: yaml.Node | None, index: Any) -> yaml.Node | None:
        self.depth += 1
        try:
            if self.depth > MAX_DEPTH:
                raise yaml.composer.ComposerError(None, None, f"values nested more than {MAX_DEPTH} levels deep; a "
                                                  "run config nests a few levels", self.peek_event().start_mark)
            return super().compose_node(parent, index)
        finally:
            self.depth -= 1

    def construct_mapping(self, node: yaml.MappingNode, deep: bool = False) -> dict[Any, Any]:
        seen: set[Any] = set()
        for key_node, _ in node.value:
            if key_node.tag == "tag:yaml.org,2002:merge":
                continue
            key = self.construct_object(key_node, deep=True)
            if not isinstance(key, Hashable):
                continue  # the safe loader refuses it itself
            if key in seen:
                raise yaml.constructor.ConstructorError(
                    "in a mapping", node.start_mark, f"key {key!r} appears twice; keep one", key_node.start_mark)
            seen.add(key)
        return super().construct_mapping(node, deep=deep)


def _expanded_values(node: yaml.Node, sizes: dict[int, int]) -> int:
    """Return the values `node` stands for once every alias in it is expanded (`sizes`: by node id, shared across the
    document, so each node is counted once however often aliases repeat it); an alias inside itself counts as
    beyond any limit."""
    if id(node) in sizes:
        return sizes[id(node)]
    sizes[id(node)] = 2**62  # while counting: reached again only through an alias to an enclosing node
    children = node.value if isinstance(node, yaml.CollectionNode) else []
    items = [part for child in children for part in (child if isinstance(child, tuple) else (child,))]
    sizes[id(node)] = total = 1 + sum(_expanded_values(item, sizes) for item in items)
    return total


def format_errors(err: ValidationError, data: Any = None) -> list[str]:
    """Return one `key path: message` line per validation error, e.g. `pairs[1].positive: field required`.

    With the validated `data`, list positions print as `[i]` and mapping keys as `.key` (`sae.12`).
    """
    lines = []
    errors = err.errors(include_url=False)
    failed = [error["loc"] for error in errors]
    for error in errors:
        loc = error["loc"]
        if error["type"] == "too_short" and any(other[:len(loc)] == loc != other for other in failed):
            continue  # a list too short only because its bad items (reported) were left out
        key = _key_path(loc, data)
        message = error_message(error).removeprefix("Value error, ")
        message = message[:1].lower() + message[1:]
        if error["type"] == "extra_forbidden":
            section, _, field = key.partition(".")
            instead = SUPPLIED.get(section, {}).get(field) or MOVED.get(section, {}).get(field)
            current = FORMER_NAMES.get(section, {}).get(field)
            message = (f"set by the run config: use `{instead}`" if instead
                       else f"the former name of `{current}`, given beside it; keep only `{current}`" if current
                       else "unknown key (check its spelling and section)")
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
    with atomic_path(path) as tmp:
        tmp.write_text(run_config_text(config), encoding="utf-8")
    return path


def run_config_text(config: RunConfig) -> str:
    """Return the YAML `write_run_config` writes for `config`."""
    return yaml.safe_dump(config.model_dump(mode="json", exclude_defaults=True), sort_keys=False, allow_unicode=True)


def claim_config_file(path: Path, config: RunConfig) -> None:
    """Raise unless `path` is free or already holds `config` as `write_run_config` writes it: another run's config
    is never overwritten."""
    if path.exists() and (not path.is_file() or path.read_bytes() != run_config_text(config).encode()):
        raise ValueError(f"{path}: already holds another run config (or is not a file), which would be overwritten; "
                         "choose another folder, or move the file away")


SHARED_CONFIGS = ".runs"  # under a bucket output root: the run configs handed to workers on other machines


def share_run_config(config: RunConfig) -> str | None:
    """Put `config` in its bucket output root for workers on other machines; return its URL (None: a local root).

    Paths in the mirrors are written as their URLs, so each worker reads them through its own mirror; other
    paths stay as they are and must name the same files on every machine. The name carries the content's
    hash, so a run never reads another run's config.
    """
    url = url_of(config.output_root)
    if url is None:
        return None
    text = yaml.safe_dump(portable(config.model_dump(mode="json", exclude_defaults=True)), sort_keys=False,
                          allow_unicode=True).encode("utf-8")
    shared = f"{url}/{SHARED_CONFIGS}/{config.name}-{hashlib.sha256(text).hexdigest()[:16]}.yaml"
    fs, path = object_path(shared)
    fs.pipe_file(path, text)
    return shared
