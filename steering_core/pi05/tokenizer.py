"""pi0.5 prompts: PaliGemma tokenisation in the two formats openpi trains with (spec 4).

The tokenizer is PaliGemma's SentencePiece model (openpi reads `paligemma_tokenizer.model`) or its Hugging Face
`tokenizer.json` (lerobot's preprocessor loads `google/paligemma-3b-pt-224`); both give the same ids (spec 17.5).
`sentencepiece` and `tokenizers` are imported when a tokenizer is opened, so importing this module stays cheap.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from enum import Enum
from pathlib import Path
from typing import Protocol

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
HF_TOKENIZER_FILE = "tokenizer.json"  # a Hugging Face tokenizer folder's file
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


class Encoder(Protocol):
    """What a prompt needs of a tokenizer file: ids without special tokens, and which of them cover a text span."""

    path: Path

    def vocab_size(self) -> int: ...

    def encode(self, text: str) -> list[int]: ...

    def encode_span(self, text: str, begin: int, end: int) -> tuple[list[int], list[int]]:
        """Return the ids of `text` and the indices of those overlapping characters [begin, end)."""
        ...


class PromptTokenizer:
    """PaliGemma tokenizer (SentencePiece model or tokenizer.json) that builds pi0.5 prompts and finds the
    instruction tokens."""

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
        self._encoder = open_encoder(self.path)
        self._newline_ids = self._encoder.encode(NEWLINE)

    @property
    def vocab_size(self) -> int:
        """Return the number of pieces; every id is below it (must not exceed the model's vocab_size)."""
        return self._encoder.vocab_size()

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
            body = self._encoder.encode(text)
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
        """Return BOS + ids of the whole prompt and the span of pieces overlapping the instruction's characters.

        The prompt is encoded in one call, as openpi and lerobot do; the instruction's first word may then tokenise
        differently than alone, so the span comes from piece offsets, not from a subsequence search.
        """
        begin = len(TASK_PREFIX)
        ids, inside = self._encoder.encode_span(prompt, begin, begin + len(text))
        # +1: language index 0 is BOS
        span = (inside[0] + 1, inside[-1] + 2) if inside else (1, 1)
        return [BOS_ID, *ids], span


class SentencePieceEncoder:
    """PaliGemma's SentencePiece model (`paligemma_tokenizer.model`)."""

    def __init__(self, path: Path):
        import sentencepiece  # deferred: only tokenizing needs it

        self.path = path
        self._processor = sentencepiece.SentencePieceProcessor()
        try:
            self._processor.load(str(path))
        except (OSError, RuntimeError) as err:
            raise ValueError(f"{path}: not a SentencePiece model ({err})") from None
        processor = self._processor
        self.special_ids = {"pad": processor.pad_id(), "eos": processor.eos_id(), "bos": processor.bos_id()}
        self.newline_id = processor.piece_to_id(NEWLINE) if processor.encode_as_pieces(NEWLINE) == [NEWLINE] else None

    def vocab_size(self) -> int:
        return self._processor.vocab_size()

    def encode(self, text: str) -> list[int]:
        return self._processor.encode(text)

    def pieces(self, text: str) -> list[str]:
        return self._processor.encode_as_pieces(text)

    def encode_span(self, text: str, begin: int, end: int) -> tuple[list[int], list[int]]:
        proto = self._processor.encode(text, return_type="proto")
        # SentencePiece's offsets count bytes
        byte_begin, byte_end = len(text[:begin].encode("utf-8")), len(text[:end].encode("utf-8"))
        pieces = list(proto.pieces)
        inside = [i for i, piece in enumerate(pieces) if piece.begin < byte_end and piece.end > byte_begin]
        return [piece.id for piece in pieces], inside


class HuggingFaceEncoder:
    """A Hugging Face `tokenizer.json` of PaliGemma (what lerobot's preprocessor loads), read with `tokenizers`."""

    def __init__(self, path: Path):
        from tokenizers import Tokenizer  # deferred: only tokenizing needs it

        self.path = path
        try:
            self._tokenizer = Tokenizer.from_file(str(path))
        except Exception as err:  # tokenizers raises its own Exception type for any malformed file
            raise ValueError(f"{path}: not a Hugging Face tokenizer.json ({err})") from None
        token_id = self._tokenizer.token_to_id
        # BOS is what the file's post-processor prepends (lerobot tokenizes with add_special_tokens=True); the
        # pieces are named <bos>/<eos> in PaliGemma's file and <s>/</s> in a SentencePiece conversion
        with_bos = self._tokenizer.encode("a", add_special_tokens=True).ids
        bos = with_bos[0] if len(with_bos) > len(self.encode("a")) else None
        eos = token_id("<eos>") if token_id("<eos>") is not None else token_id("</s>")
        self.special_ids = {"pad": token_id("<pad>"), "eos": eos, "bos": bos}
        self.newline_id = token_id(NEWLINE) if self.pieces(NEWLINE) == [NEWLINE] else None

    def vocab_size(self) -> int:
        return self._tokenizer.get_vocab_size(with_added_tokens=True)

    def encode(self, text: str) -> list[int]:
        return self._tokenizer.encode(text, add_special_tokens=False).ids

    def pieces(self, text: str) -> list[str]:
        return self._tokenizer.encode(text, add_special_tokens=False).tokens

    def encode_span(self, text: str, begin: int, end: int) -> tuple[list[int], list[int]]:
        encoding = self._tokenizer.encode(text, add_special_tokens=False)
        inside = [i for i, (start, stop) in enumerate(encoding.offsets) if start < end and stop > begin]
        return encoding.ids, inside


def open_encoder(path: Path) -> SentencePieceEncoder | HuggingFaceEncoder:
    """Return the tokenizer at `path` (a SentencePiece model, a tokenizer.json, or a folder holding one) after
    checking the PaliGemma facts marked [U] in the spec."""
    if path.is_dir():
        path = path / HF_TOKENIZER_FILE
    if not path.is_file():
        raise FileNotFoundError(
            f"{path}: tokenizer not found; pass PaliGemma's SentencePiece paligemma_tokenizer.model "
            f"(gs://big_vision/paligemma_tokenizer.model) or its Hugging Face {HF_TOKENIZER_FILE} (or the folder "
            "holding it, e.g. google/paligemma-3b-pt-224 in a local Hugging Face cache)"
        )
    encoder = HuggingFaceEncoder(path) if path.suffix == ".json" else SentencePieceEncoder(path)
    problems = [f"{name} id is {found}, expected {expected}"
                for (name, found), expected in zip(encoder.special_ids.items(), (PAD_ID, EOS_ID, BOS_ID))
                if found != expected]
    if encoder.newline_id is None:
        problems.append(f"'\\n' encodes as pieces {encoder.pieces(NEWLINE)}, expected the single piece '\\n'")
    elif encoder.vocab_size() == PALIGEMMA_VOCAB_SIZE and encoder.newline_id != PALIGEMMA_NEWLINE_ID:
        problems.append(f"'\\n' has id {encoder.newline_id}, expected {PALIGEMMA_NEWLINE_ID}")
    first = encoder.pieces("a")
    if first and first[0].startswith(WORD_BOUNDARY):
        problems.append(f"'a' encodes as {first}: the model adds a dummy-prefix '{WORD_BOUNDARY}', Gemma's does not")
    if problems:
        raise ValueError(f"{path}: not a PaliGemma-style tokenizer: " + "; ".join(problems) +
                         f"; pass paligemma_tokenizer.model or PaliGemma's {HF_TOKENIZER_FILE}")
    logger.info("tokenizer %s: %d pieces", path, encoder.vocab_size())
    return encoder
