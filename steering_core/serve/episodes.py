"""Episodes a client reports with openpi's control messages (its main-branch client since 2025).

`{"__ctrl__": "episode_start", "__experiment__": str, "__task__": str, "__episode_id__": int}` opens an episode
on the connection and `{"__ctrl__": "episode_end", "__success__": bool}` closes it; each is answered, as openpi's
server does, with `{"__ack__": <ctrl>}`. A missing field takes openpi's server default; a wrong-typed or unknown
one, or another `__ctrl__` value, is a RequestError. An episode is recorded when it ends: by episode_end (with
its success), by the next episode_start or by the connection closing (success None: never reported). An
episode_end without an episode_start is recorded too, with no experiment, task, id or start time.
"""

from __future__ import annotations

import contextlib
import json
import logging
import time
from collections import deque
from collections.abc import Mapping
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from steering_core.serve.request import RequestError

logger = logging.getLogger(__name__)

CTRL_KEY = "__ctrl__"
ACK_KEY = "__ack__"
EPISODES_KEPT = 10_000  # finished episodes a server keeps in memory
MAX_FIELD_CHARS = 1000  # an experiment or task name; LIBERO's instructions are under 100 characters
# the episodes file: past this size it moves to <file>.1 (replacing the older one) and a new file begins, so the
# server's disk use stays under twice this (about 0.3 KB an episode: a file holds ~200,000)
MAX_EPISODES_FILE_BYTES = 64 * 2**20
# message key -> (record field, accepted types, openpi's server default)
START_FIELDS = {"__experiment__": ("experiment", (str,), "unknown"), "__task__": ("task", (str,), ""),
                "__episode_id__": ("episode_id", (int, np.integer), -1)}
END_FIELDS = {"__success__": ("success", (bool, np.bool_), False)}


@dataclass
class Episode:
    """One episode of one connection; times are Unix seconds (None: no episode_start was sent)."""

    client: str
    experiment: str | None = None
    task: str | None = None
    episode_id: int | None = None
    start_time: float | None = None
    inferences: int = 0
    success: bool | None = None
    end_time: float | None = None
    ended_by: str | None = None  # "episode_end", "episode_start" (the next one began) or "disconnect"


class EpisodeNotRecorded(Exception):
    """An episode kept in memory whose line could not be written to the episodes file; str() is the client's line."""


class EpisodeLog:
    """The server's finished episodes: the last EPISODES_KEPT in `records`, every one logged and, with a
    `path`, appended to it as one JSON line (written whole and flushed; the file rotates at
    MAX_EPISODES_FILE_BYTES). A failed write (a full disk, the file removed with its folder) is logged naming the
    file and raised as EpisodeNotRecorded; the server keeps serving and the next episode tries again."""

    def __init__(self, path: Path | None = None) -> None:
        self.path = path
        self.records: deque[dict[str, Any]] = deque(maxlen=EPISODES_KEPT)
        if path is not None:
            path.open("a", encoding="utf-8").close()  # an unwritable path fails at start, not at the first episode

    def add(self, episode: Episode) -> None:
        record = asdict(episode)
        self.records.append(record)
        logger.info("episode %s of %r (task %r) from %s: success %s, %d inference(s), ended by %s",
                    episode.episode_id, episode.experiment, episode.task, episode.client, episode.success,
                    episode.inferences, episode.ended_by)
        if self.path is not None:
            try:
                self._append(json.dumps(record) + "\n")
            except OSError as err:
                reason = err.strerror or str(err)
                logger.warning("episodes file %s: episode %s of %s not written (%s); it is kept in memory only",
                               self.path, episode.episode_id, episode.client, reason)
                raise EpisodeNotRecorded(f"the server could not record the episode: {reason} (its episodes file; "
                                         "the server keeps serving)") from None

    def _append(self, line: str) -> None:
        """Append one line to the episodes file, first moving a full file to <file>.1."""
        if self.path.is_file() and self.path.stat().st_size + len(line.encode()) > MAX_EPISODES_FILE_BYTES:
            rotated = self.path.with_name(self.path.name + ".1")
            self.path.replace(rotated)
            logger.info("episodes file %s reached %d MiB: moved to %s, a new one begins", self.path,
                        MAX_EPISODES_FILE_BYTES // 2**20, rotated)
        with self.path.open("a", encoding="utf-8") as f:
            f.write(line)


class ConnectionEpisodes:
    """The episode state of one connection: answers its control messages and counts its inferences."""

    def __init__(self, client: str, log: EpisodeLog) -> None:
        self.client, self.log = client, log
        self.current: Episode | None = None
        self.inferences = 0  # since the connection opened or the last episode began or ended

    def control(self, message: Mapping[str, Any]) -> dict[str, str]:
        """Apply one control message and return the reply; raise RequestError for a malformed one, and
        EpisodeNotRecorded (after applying it) when the episode it ended could not be written."""
        ctrl = message[CTRL_KEY]
        if not isinstance(ctrl, str):
            raise RequestError(CTRL_KEY, f"expected a str, got {type(ctrl).__name__}")
        if ctrl == "episode_start":
            fields = _fields(message, START_FIELDS)
            ended = self._end(None, "episode_start")
            self.current = Episode(self.client, start_time=time.time(), **fields)
            self._record(ended)
        elif ctrl == "episode_end":
            fields = _fields(message, END_FIELDS)
            if self.current is None:
                logger.warning("episode_end from %s without episode_start: recorded without experiment, task, id "
                               "or start time", self.client)
                self.current = Episode(self.client)
            self._record(self._end(fields["success"], "episode_end"))
        else:
            raise RequestError(CTRL_KEY, f"unknown control message {ctrl!r}; expected 'episode_start' or "
                                         "'episode_end'")
        return {ACK_KEY: ctrl}

    def inferred(self) -> None:
        self.inferences += 1

    def close(self) -> None:
        """Record the open episode, if any, as ended by the connection closing (a failed write is only logged)."""
        with contextlib.suppress(EpisodeNotRecorded):
            self._record(self._end(None, "disconnect"))

    def _end(self, success: bool | None, ended_by: str) -> Episode | None:
        """Return the open episode (None: none) ended, and begin counting afresh."""
        ended = self.current
        if ended is not None:
            ended.inferences, ended.success = self.inferences, success
            ended.end_time, ended.ended_by = time.time(), ended_by
        self.current, self.inferences = None, 0
        return ended

    def _record(self, episode: Episode | None) -> None:
        if episode is not None:
            self.log.add(episode)


def _fields(message: Mapping[str, Any], spec: dict[str, tuple]) -> dict[str, Any]:
    unknown = sorted(str(k) for k in message if k != CTRL_KEY and k not in spec)
    if unknown:
        raise RequestError(message[CTRL_KEY], f"unknown key(s) {unknown}; expected {list(spec)}")
    fields = {}
    for key, (name, types, default) in spec.items():
        value = message.get(key, default)
        if not isinstance(value, types) or (bool not in types and isinstance(value, bool)):
            raise RequestError(key, f"expected {types[0].__name__}, got {type(value).__name__} {value!r:.60}")
        if isinstance(value, str) and len(value) > MAX_FIELD_CHARS:
            raise RequestError(key, f"{len(value)} characters; expected at most {MAX_FIELD_CHARS}")
        fields[name] = value.item() if isinstance(value, np.generic) else value
    return fields
