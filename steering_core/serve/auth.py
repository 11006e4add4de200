"""The api key a server may require: the header `Authorization: Api-Key <key>` openpi's client sends on the
websocket upgrade, compared in constant time."""

from __future__ import annotations

import hmac
import os
from collections.abc import Mapping
from pathlib import Path

from steering_core.storage.fileio import read_text

API_KEY_ENV = "LATENT_STEERING_API_KEY"
HEADER = "Authorization"
SCHEME = "Api-Key"


def read_api_key(path: Path | None, environ: Mapping[str, str] = os.environ) -> str | None:
    """Return the key in `path` (surrounding whitespace stripped), else in $LATENT_STEERING_API_KEY, else None.

    Raises FileNotFoundError for a missing file, ValueError naming it for a binary one, and ValueError for an empty key or one that cannot travel in an HTTP header (printable ASCII, no spaces).
    """
    if path is not None:
        key, where = read_text(path, "the api key: one line of printable ASCII").strip(), str(path)
    elif API_KEY_ENV in environ:
        key, where = environ[API_KEY_ENV].strip(), f"${API_KEY_ENV}"
    else:
        return None
    if not key:
        raise ValueError(f"{where} is empty; put the api key in it, or serve without one")
    if not all("!" <= c <= "~" for c in key):
        raise ValueError(f"{where}: the api key must be printable ASCII without spaces (it travels in an HTTP header)")
    return key


def authorized(values: list[str], key: str) -> bool:
    """Return True when the request's Authorization header values are exactly one `Api-Key <key>`."""
    given = values[0].encode() if len(values) == 1 else b""
    return hmac.compare_digest(given, f"{SCHEME} {key}".encode())
