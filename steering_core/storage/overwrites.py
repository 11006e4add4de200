"""One rule for every command and run: an output never overwrites an input.

An output path that is, contains or lies inside an input of the same command (or run config) is refused before
anything is written, in one line naming both. Paths are compared after resolving symlinks and `..`, so two spellings
of one place are one place.
"""

from __future__ import annotations

import os
from collections.abc import Iterable, Mapping
from pathlib import Path

PathLike = str | os.PathLike
Named = Mapping[str, PathLike | Iterable[PathLike] | None]  # a name (option, config key) -> its path(s)


def _paths(named: Named) -> list[tuple[str, Path, Path]]:
    """Return (name, path as given, path resolved) of every path in `named`; None is skipped."""
    out = []
    for name, value in named.items():
        values = [] if value is None else [value] if isinstance(value, str | os.PathLike) else list(value)
        out += [(name, Path(path), Path(path).expanduser().resolve()) for path in values if path is not None]
    return out


def overwrite_problem(outputs: Named, inputs: Named, *, of: str = "the command") -> str | None:
    """Return the line refusing the first output that is, contains or lies inside an input, else None.

    `outputs` and `inputs` map a name (an option such as `--output`, a config key) to a path, several paths, or None.
    """
    sources = _paths(inputs)
    for out_name, out, out_real in _paths(outputs):
        for in_name, given, real in sources:
            relation = ("is" if out_real == real else "lies inside" if real in out_real.parents
                        else "contains" if out_real in real.parents else None)
            if relation is not None:
                return (f"{out_name} {out} {relation} {in_name} {given}, an input of {of}: an input is read, never "
                        f"written; give {out_name} a place apart from every input")
    return None


def check_no_overwrite(outputs: Named, inputs: Named, *, of: str = "the command") -> None:
    """Raise ValueError with `overwrite_problem`'s line when an output is, contains or lies inside an input."""
    if (problem := overwrite_problem(outputs, inputs, of=of)) is not None:
        raise ValueError(problem)
