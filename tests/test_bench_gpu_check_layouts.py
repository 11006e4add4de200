"""The GPU check on a given checkpoint (--checkpoint, --tokenizer, --layout, --arch-file) at its --quick size on the
CPU: lerobot's layout runs and passes, the result records the checkpoint, and bad combinations are refused."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest
import torch
from safetensors.torch import load_file, save_file

REPO_ROOT = Path(__file__).resolve().parent.parent
if str(REPO_ROOT) not in sys.path:  # bench/ is a folder of scripts at the repository root, not an installed package
    sys.path.insert(0, str(REPO_ROOT))

from bench import gpu_check  # noqa: E402
from bench.common import Result  # noqa: E402
from bench.seed_pi05 import SeedPi05  # noqa: E402
from steering_core.pi05.layouts import EMBED_TOKENS_KEY, LM_HEAD_KEY, LayoutName  # noqa: E402
from steering_core.synthetic.pi05 import tiny_arch, write_pi05_checkpoint  # noqa: E402

LEROBOT = REPO_ROOT / "tests" / "fixtures" / "lerobot_golden"
MODEL, TOKENIZER = LEROBOT / "model", LEROBOT / "tokenizer" / "tokenizer.json"


@pytest.fixture
def arch_file(tmp_path: Path) -> Path:
    path = tmp_path / "arch.json"
    path.write_text(tiny_arch(512).model_dump_json())  # the lerobot fixture's dimensions
    return path


def given(tmp_path: Path, arch_file: Path, *extra: str) -> list[str]:
    return ["--quick", f"--cache-dir={tmp_path / 'cache'}", f"--json={tmp_path / 'check.json'}",
            "--checkpoint", str(MODEL), "--tokenizer", str(TOKENIZER), "--arch-file", str(arch_file), *extra]


@pytest.mark.slow
def test_quick_check_on_a_lerobot_checkpoint_records_its_layout_and_passes(tmp_path, arch_file):
    result = gpu_check.main(given(tmp_path, arch_file, "--sections", "peak", "capture", "server"))
    payload = json.loads((tmp_path / "check.json").read_text())
    assert Result.from_json(payload) == result
    assert payload["met"] and payload["checks"]["passed"] and payload["checks"]["failed"] == []
    sections = payload["checks"]["sections"]
    assert list(sections) == ["peak", "capture", "server"]
    comparisons = [c for section in sections.values() for c in section["comparisons"]]
    assert [c["case"] for c in comparisons] == ["capture rows vs seed, batch 2", "capture rows vs seed, batch 4",
                                                "served steered actions vs direct infer"]
    assert all(c["passed"] and c["error"] <= c["tolerance"] for c in comparisons)
    record = payload["checks"]["checkpoint"]
    assert record["layout"] == LayoutName.LEROBOT.value and record["layout_option"] == "auto"
    assert Path(record["model_file"]) == MODEL / "model.safetensors"
    assert record["tokenizer"] == str(TOKENIZER) and record["arch"] == tiny_arch(512).model_dump()
    assert record["sections"] == ["capture", "server"] and record["generated_input_sections"] == ["peak"]
    note = next(note for note in payload["notes"] if note.startswith("checkpoint: "))
    assert "(lerobot layout)" in note and "own generated inputs (not the checkpoint) in peak." in note
    assert f"--checkpoint {MODEL} --tokenizer {TOKENIZER}" in payload["command"]
    assert not (tmp_path / "cache" / "pi05-tiny-bf16").exists()  # nothing generated for the policy sections


def test_seed_reads_lerobot_names_as_openpi_ones(tmp_path):
    arch = tiny_arch()
    openpi = write_pi05_checkpoint(tmp_path / "openpi", arch)
    tensors = load_file(str(openpi / "model.safetensors"))
    lerobot = tmp_path / "lerobot"
    lerobot.mkdir()
    stored = {"model." + name: tensor for name, tensor in tensors.items()}
    stored["model." + EMBED_TOKENS_KEY] = tensors[LM_HEAD_KEY].clone()  # lerobot keeps both tied tables
    save_file(stored, str(lerobot / "model.safetensors"))
    (lerobot / "config.json").write_text(json.dumps({"type": "pi05"}))
    cpu = torch.device("cpu")
    want = SeedPi05.from_checkpoint(openpi, arch, cpu).state_dict()
    got = SeedPi05.from_checkpoint(lerobot, arch, cpu, layout="lerobot").state_dict()
    assert got.keys() == want.keys()
    assert all(got[name].dtype == want[name].dtype and torch.equal(got[name], want[name]) for name in want)


def refusal(argv: list[str]) -> str:
    with pytest.raises(SystemExit) as exit_info:
        gpu_check.main(argv)
    return str(exit_info.value.code)


def test_a_forced_layout_the_folder_contradicts_is_refused_in_one_line(tmp_path, arch_file):
    text = refusal(given(tmp_path, arch_file, "--layout", "openpi", "--sections", "capture"))
    assert text.startswith("bench.gpu_check: --checkpoint ") and "\n" not in text
    assert "the layout was set to openpi, but the file is lerobot's" in text
    assert not (tmp_path / "check.json").exists()


def test_a_section_the_checkpoint_cannot_run_is_refused_in_one_line(tmp_path):
    one_layer = tmp_path / "one-layer.json"  # the server steers layer 1: a one-layer model has none
    one_layer.write_text(tiny_arch(512).model_copy(update={"depth": 1}).model_dump_json())
    text = refusal(given(tmp_path, one_layer, "--sections", "server"))
    assert text.startswith("bench.gpu_check: the server section") and text.endswith("leave server out")
    assert "\n" not in text and not (tmp_path / "check.json").exists()


@pytest.mark.parametrize("argv", [["--tokenizer", str(TOKENIZER)], ["--layout", "lerobot"],
                                  ["--checkpoint", str(MODEL)]])
def test_options_describing_a_checkpoint_need_one_and_it_needs_a_tokenizer(tmp_path, argv, capsys):
    with pytest.raises(SystemExit) as exit_info:
        gpu_check.main(["--quick", f"--cache-dir={tmp_path}", *argv])
    assert exit_info.value.code == 2  # argparse's usage error
    assert "--checkpoint" in capsys.readouterr().err
