"""Prompt formats, instruction spans and tokenizer checks, on a tiny PaliGemma-style SentencePiece model."""

from __future__ import annotations

import io
import logging

import numpy as np
import pytest
import sentencepiece

from steering_core.pi05 import PromptFormat, PromptTokenizer, TokenizedPrompt
from steering_core.synthetic.pi05 import tiny_arch
from steering_core.synthetic.tokenizer import write_tokenizer

TASK = "open the top drawer of the cabinet"
NEWLINE_ID = 4  # the synthetic model's first user-defined piece, right after pad, eos, bos, unk


@pytest.fixture(scope="module")
def model_path(tmp_path_factory):
    return write_tokenizer(tmp_path_factory.mktemp("tok") / "tokenizer.model")


@pytest.fixture(scope="module")
def sp(model_path):
    return sentencepiece.SentencePieceProcessor(model_file=str(model_path))


def test_synthetic_tokenizer_has_gemma_conventions(sp):
    assert (sp.pad_id(), sp.eos_id(), sp.bos_id(), sp.unk_id()) == (0, 1, 2, 3)
    assert sp.piece_to_id("\n") == NEWLINE_ID and sp.encode("\n") == [NEWLINE_ID]
    assert sp.encode_as_pieces("Zürich") and sp.decode(sp.encode("Zürich")) == "Zürich"  # byte fallback
    assert sp.vocab_size() <= tiny_arch().vocab_size


def test_libero_prompt_is_bos_instruction_newline(model_path, sp):
    prompt = PromptTokenizer(model_path, max_len=32).tokenize(f"  {TASK.replace(' ', '_', 2)}\n")
    body = sp.encode(TASK)  # cleaned: stripped, "_" and "\n" -> " "
    n = len(body)
    assert isinstance(prompt, TokenizedPrompt)
    assert prompt.ids.dtype == np.int64 and prompt.mask.dtype == bool and prompt.ids.shape == (32,)
    assert prompt.ids.tolist() == [2, *body, NEWLINE_ID] + [0] * (32 - n - 2)
    assert prompt.mask.tolist() == [True] * (n + 2) + [False] * (32 - n - 2)
    assert prompt.n_valid == n + 2
    assert prompt.instruction == (1, 1 + n)
    assert sp.decode(prompt.ids[1 : 1 + n].tolist()) == TASK


def test_libero_prompt_ignores_the_state(model_path):
    tokenizer = PromptTokenizer(model_path, max_len=32)
    with_state, without = tokenizer.tokenize(TASK, np.full(8, 0.3)), tokenizer.tokenize(TASK)
    assert np.array_equal(with_state.ids, without.ids) and with_state.instruction == without.instruction


def test_discrete_state_prompt_text_bins_and_span(model_path, sp):
    tokenizer = PromptTokenizer(model_path, max_len=80, prompt_format=PromptFormat.DISCRETE_STATE)
    # bins by hand: floor((x + 1) * 128); -1 below -1; 255 from 0.9921875 up, no clipping of x
    state = np.array([-1.5, -1.0, -0.5, 0.0, 0.5, 0.99, 0.9921875, 2.0])
    text = tokenizer.prompt_text("open the drawer", state)
    assert text == "Task: open the drawer, State: -1 0 64 128 192 254 255 255;\nAction: "
    prompt = tokenizer.tokenize("open the drawer", state)
    whole = sp.encode(text)  # openpi encodes the whole prompt in one call
    assert prompt.ids[: prompt.n_valid].tolist() == [2, *whole]
    start, end = prompt.instruction
    assert sp.decode(prompt.ids[start:end].tolist()) == " open the drawer"
    assert sp.id_to_piece(int(prompt.ids[start - 1])) == ":"  # end of "Task:"
    assert sp.id_to_piece(int(prompt.ids[end])) == ","  # start of ", State:"
    # after "Task:" the first word is "▁open..." pieces, not those of "open" alone: no subsequence search
    assert prompt.ids[start:end].tolist() != sp.encode("open the drawer")


def test_discrete_state_format_needs_a_state(model_path):
    tokenizer = PromptTokenizer(model_path, prompt_format="discrete_state")
    with pytest.raises(ValueError, match="the discrete_state prompt format needs the quantile-normalised state"):
        tokenizer.tokenize(TASK)
    with pytest.raises(ValueError, match=r"state must be a finite 1-D vector, found shape \(2, 2\)"):
        tokenizer.tokenize(TASK, np.zeros((2, 2)))


def test_long_prompt_is_truncated_with_a_warning(model_path, sp, caplog):
    with caplog.at_level(logging.WARNING):
        prompt = PromptTokenizer(model_path, max_len=5).tokenize(TASK)
    assert "truncated to 5" in caplog.text
    assert prompt.n_valid == 5 and prompt.mask.all()
    assert prompt.ids.tolist() == [2, *sp.encode(TASK)[:4]]
    assert prompt.instruction == (1, 5)


def test_missing_tokenizer_is_file_not_found(tmp_path):
    missing = tmp_path / "paligemma_tokenizer.model"
    with pytest.raises(FileNotFoundError, match=f"{missing}: tokenizer not found"):
        PromptTokenizer(missing)


def test_not_a_sentencepiece_file(tmp_path):
    bad = tmp_path / "bad.model"
    bad.write_text("hello")
    with pytest.raises(ValueError, match=f"{bad}: not a SentencePiece model"):
        PromptTokenizer(bad)


def test_non_paligemma_conventions_are_one_clear_error(tmp_path):
    # a stock SentencePiece setup: bos 1, eos 2, no pad, dummy prefix, newline not a piece
    model = io.BytesIO()
    sentencepiece.SentencePieceTrainer.train(
        sentence_iterator=iter(["open the drawer", "close the drawer", "a b c"]),
        model_writer=model,
        vocab_size=40,
        hard_vocab_limit=False,
        bos_id=1,
        eos_id=2,
        unk_id=0,
        minloglevel=2,
    )
    path = tmp_path / "stock.model"
    path.write_bytes(model.getvalue())
    with pytest.raises(ValueError) as err:
        PromptTokenizer(path)
    message = str(err.value)
    assert message.startswith(f"{path}: not a PaliGemma-style tokenizer: pad id is -1, expected 0; ")
    assert "eos id is 2, expected 1" in message
    assert "bos id is 1, expected 2" in message
    assert "'\\n' encodes as pieces" in message
    assert "adds a dummy-prefix" in message
    assert message.endswith("pass paligemma_tokenizer.model or PaliGemma's tokenizer.json")
