"""A tiny SentencePiece model with PaliGemma's conventions, trained on LIBERO-like instructions.

Gemma-style ids (pad 0, eos 1, bos 2, unk 3), byte fallback, "\\n" as its own piece, no dummy prefix and
no text normalisation, so `steering_core.pi05.PromptTokenizer` accepts it like the real file.
"""

from __future__ import annotations

import io
import os
from collections.abc import Iterable
from pathlib import Path

from steering_core.storage.fileio import atomic_path

TOKENIZER_FILE = "tokenizer.model"
VOCAB_SIZE = 384  # 256 byte pieces + 4 specials + "\n" + room for characters and merges; < tiny_arch's 512

LIBERO_INSTRUCTIONS = (
    "open the top drawer of the cabinet",
    "close the top drawer of the cabinet",
    "open the middle drawer of the cabinet",
    "put the bowl on the plate",
    "put the bowl on the stove",
    "put the wine bottle on top of the cabinet",
    "pick up the black bowl between the plate and the ramekin and place it on the plate",
    "pick up the alphabet soup and place it in the basket",
    "put both the alphabet soup and the tomato sauce in the basket",
    "turn on the stove and put the moka pot on it",
    "put the yellow and white mug in the microwave and close it",
    "open the microwave",
    "close the microwave",
    "push the plate to the front of the stove",
    "put the cream cheese in the bowl",
)
# Scaffolding of the discrete-state prompt, so "Task:", digits and "Action:" get pieces of their own.
_FORMAT_LINES = (
    "Task: open the drawer, State: 0 1 2 3 4 5 6 7 8 9;",
    "Action: ",
    "State: 128 255 -1 64 200 17;",
)


def write_tokenizer(
    path: str | os.PathLike,
    instructions: Iterable[str] = LIBERO_INSTRUCTIONS,
    vocab_size: int = VOCAB_SIZE,
) -> Path:
    """Train a BPE SentencePiece model on `instructions` (plus prompt scaffolding) and write it; return the path."""
    import sentencepiece  # deferred: only this builder and tokenizing need it

    model = io.BytesIO()
    sentencepiece.SentencePieceTrainer.train(
        sentence_iterator=iter([*instructions, *_FORMAT_LINES]),
        model_writer=model,
        model_type="bpe",  # Gemma's model type
        vocab_size=vocab_size,
        hard_vocab_limit=False,  # a handful of sentences may not support every merge
        pad_id=0,
        eos_id=1,
        bos_id=2,
        unk_id=3,
        byte_fallback=True,
        user_defined_symbols=["\n"],
        add_dummy_prefix=False,
        normalization_rule_name="identity",
        remove_extra_whitespaces=False,
        split_digits=True,
        allow_whitespace_only_pieces=True,
        num_threads=1,
        minloglevel=2,  # quiet: training logs go to stderr otherwise
    )
    path = Path(path)
    with atomic_path(path) as tmp:
        tmp.write_bytes(model.getvalue())
    return path
