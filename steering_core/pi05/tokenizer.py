"""pi0.5 prompts: PaliGemma SentencePiece tokenisation in the two formats openpi trains with (spec 4).

`sentencepiece` is imported when a tokenizer is opened, so importing this module stays cheap.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from enum import Enum
from pathlib import Path
from typing import Any

import numpy as np

from steering_core.pi05.norm_stats import discretize_state

logger = logging.getLogger(__name__)

MAX_TOKEN_LEN = 200  # pi0.5's max_token_len (pi0 used 48)
PAD_ID = 0  # right padding (openpi pads the ids with 0 and the mask with False)
EOS_ID = 1
BOS_ID = 2
NEWLINE = "\n"  # pi05_libero's "start of answer" token, encoded on its own
PALIGEMMA_NEWLINE_ID = 108  # "\n" in the released 257152-piece PaliGemma vocabulary
PALIGEMMA_VOCAB_SIZE = 257152
WORD_BOUNDARY = "\u2581"  # SentencePiece's "▁"
TASK_PREFIX = "Task: "
STATE_PREFIX = ", State: "
ACTION_SUFFIX = ";\nAction: "


class PromptFormat(str, Enum):
    """How the checkpoint was trained to read its prompt."""

    LIBERO = "libero"  # pi05_libero: BOS + instruction + "\n"; the state never enters the model
    DISCRETE_STATE = "discrete_state"  # pi05 default: "Task: ..., State: <bins>;\nAction: " (spec 4.3)


@dataclass(frozen=True)
class TokenizedPrompt:
    """One prompt as the model reads it; `instruction` is the [start, end) span of the task's own tokens."""

    ids: np.ndarray  # (max_len,) int64, right-padded with PAD_ID
    mask: np.ndarray  # (max_len,) bool, True on real tokens
    n_valid: int
    instruction: tuple[int, int]  # language indices (prefix index = n_images * tokens_per_image + index)

    def instruction_mask(self) -> np.ndarray:
        """Return (max_len,) bool: True at the instruction's tokens, where steering adds at the prompt."""
        mask = np.zeros(len(self.ids), dtype=bool)
        mask[self.instruction[0] : self.instruction[1]] = True
        return mask


def clean_instruction(task: str) -> str:
    """Return the task text as openpi feeds it: stripped, "_" and newlines replaced by spaces, case kept."""
    return task.strip().replace("_", " ").replace("\n", " ")


class PromptTokenizer:
    """PaliGemma SentencePiece tokenizer that builds pi0.5 prompts and finds the instruction tokens."""

    def __init__(
        self,
        model_path: str | os.PathLike,
        max_len: int = MAX_TOKEN_LEN,
        prompt_format: PromptFormat = PromptFormat.LIBERO,
    ):
        self.path = Path(model_path)
        self.max_len = max_len
        self.prompt_format = PromptFormat(prompt_format)
        if max_len < 1:
            raise ValueError(f"max_len {max_len} must be at least 1")
        self._processor = _open_processor(self.path)
        self._newline_ids = self._processor.encode(NEWLINE)

    @property
    def vocab_size(self) -> int:
        """Return the number of pieces; every id is below it (must not exceed the model's vocab_size)."""
        return self._processor.vocab_size()

    def prompt_text(self, task: str, state: np.ndarray | None = None) -> str:
        """Return the full prompt string (without BOS) for `task` in this tokenizer's format."""
        text = clean_instruction(task)
        if self.prompt_format is PromptFormat.LIBERO:
            return text + NEWLINE
        if state is None:
            raise ValueError(
                "the discrete_state prompt format needs the quantile-normalised state; pass state=..., or use "
                "the libero format (pi05_libero)"
            )
        state = np.asarray(state, dtype=np.float64)
        if state.ndim != 1 or not np.isfinite(state).all():
            raise ValueError(f"state must be a finite 1-D vector, found shape {state.shape}")
        bins = " ".join(str(int(b)) for b in discretize_state(state))
        return f"{TASK_PREFIX}{text}{STATE_PREFIX}{bins}{ACTION_SUFFIX}"

    def tokenize(self, task: str, state: np.ndarray | None = None) -> TokenizedPrompt:
        """Return the padded token ids, mask and instruction span of `task` (and `state`, discrete format only).

        The state is ignored by the libero format. Prompts longer than max_len are truncated with a warning,
        as openpi does.
        """
        text = clean_instruction(task)
        if self.prompt_format is PromptFormat.LIBERO:
            # openpi encodes the instruction and "\n" separately, so the span is exact by construction
            body = self._processor.encode(text)
            ids = [BOS_ID, *body, *self._newline_ids]
            start, end = 1, 1 + len(body)
        else:
            ids, (start, end) = self._encode_discrete(text, self.prompt_text(task, state))
        if len(ids) > self.max_len:
            logger.warning("prompt of %d tokens truncated to %d: %r", len(ids), self.max_len, text)
            ids = ids[: self.max_len]
        n_valid = len(ids)
        padded = np.full(self.max_len, PAD_ID, dtype=np.int64)
        padded[:n_valid] = ids
        mask = np.zeros(self.max_len, dtype=bool)
        mask[:n_valid] = True
        span = (min(start, n_valid), min(end, n_valid))
        return TokenizedPrompt(ids=padded, mask=mask, n_valid=n_valid, instruction=span)

    def _encode_discrete(self, text: str, prompt: str) -> tuple[list[int], tuple[int, int]]:
        """Return BOS + ids of the whole prompt and the span of pieces overlapping the instruction's bytes.

        The prompt is encoded in one call, as openpi does; the instruction's first word may then tokenise
        differently than alone, so the span comes from piece byte offsets, not from a subsequence search.
        """
        proto = self._processor.encode(prompt, return_type="proto")
        begin = len(TASK_PREFIX.encode("utf-8"))
        end = begin + len(text.encode("utf-8"))
        pieces = list(proto.pieces)
        inside = [i for i, piece in enumerate(pieces) if piece.begin < end and piece.end > begin]
        ids = [BOS_ID, *(piece.id for piece in pieces)]
        # +1: language index 0 is BOS
        span = (inside[0] + 1, inside[-1] + 2) if inside else (1, 1)
        return ids, span


def _open_processor(path: Path) -> Any:
    """Return a SentencePieceProcessor for `path` after checking the PaliGemma facts marked [U] in the spec."""
    if not path.is_file():
        raise FileNotFoundError(
            f"{path}: SentencePiece tokenizer not found; pass PaliGemma's paligemma_tokenizer.model "
            "(gs://big_vision/paligemma_tokenizer.model)"
        )
    import sentencepiece  # deferred: only tokenizing needs it

    processor = sentencepiece.SentencePieceProcessor()
    try:
        processor.load(str(path))
    except (OSError, RuntimeError) as err:
        raise ValueError(f"{path}: not a SentencePiece model ({err})") from None
    problems = []
    for name, found, expected in (
        ("pad id", processor.pad_id(), PAD_ID),
        ("eos id", processor.eos_id(), EOS_ID),
        ("bos id", processor.bos_id(), BOS_ID),
    ):
        if found != expected:
            problems.append(f"{name} is {found}, expected {expected}")
    newline = processor.encode_as_pieces(NEWLINE)
    if newline != [NEWLINE]:
        problems.append(f"'\\n' encodes as pieces {newline}, expected the single piece '\\n'")
    elif processor.vocab_size() == PALIGEMMA_VOCAB_SIZE and processor.piece_to_id(NEWLINE) != PALIGEMMA_NEWLINE_ID:
        problems.append(f"'\\n' has id {processor.piece_to_id(NEWLINE)}, expected {PALIGEMMA_NEWLINE_ID}")
    first = processor.encode_as_pieces("a")
    if first and first[0].startswith(WORD_BOUNDARY):
        problems.append(f"'a' encodes as {first}: the model adds a dummy-prefix '{WORD_BOUNDARY}', Gemma's does not")
    if problems:
        raise ValueError(
            f"{path}: not a PaliGemma-style tokenizer: " + "; ".join(problems) + "; pass paligemma_tokenizer.model"
        )
    logger.info("tokenizer %s: %d pieces", path, processor.vocab_size())
    return processor
