"""SAE fidelity: row metrics against naive formulas, the policy splice, the action change and its controls, the report."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from helpers_pi05 import make_batch

from steering_core.evaluate.frames import EvalFrame
from steering_core.evaluate.run import task_prompts
from steering_core.evaluate.sweep import frame_noise
from steering_core.pi05 import Pi05Policy, PromptTokenizer
from steering_core.pi05.steering import Splice, Steering
from steering_core.sae.formats import SaeConfig
from steering_core.sae.model import StandardSae, TopKSae
from steering_core.sae_quality.action_fidelity import ActionFidelity, action_fidelity, zero_ablation
from steering_core.sae_quality.fidelity import RowFidelity, row_fidelity
from steering_core.sae_quality.fidelity_report import TABLE_HEADER, ActionInputs, judge_layer, verdict
from steering_core.synthetic.pi05 import tiny_arch, write_pi05_checkpoint
from steering_core.synthetic.tokenizer import write_tokenizer

ARCH = tiny_arch()
MAX_LEN = 32
POSITIVE, NEGATIVE = "open the top drawer of the cabinet", "put the bowl on the plate"


# ----------------------------------------------------------------------------- builders


def topk_sae(d_in: int, d_sae: int = 96, k: int = 8, seed: int = 0) -> TopKSae:
    """Return a random TopK SAE (its decoder rows unit length)."""
    generator = torch.Generator().manual_seed(seed)
    w_dec = torch.randn(d_sae, d_in, generator=generator)
    w_dec /= w_dec.norm(dim=1, keepdim=True)
    weights = {"W_enc": w_dec.T.clone(), "b_enc": torch.randn(d_sae, generator=generator) * 0.1, "W_dec": w_dec,
               "b_dec": torch.randn(d_in, generator=generator) * 0.1}
    return TopKSae(SaeConfig(d_in=d_in, d_sae=d_sae, architecture="topk", k=k, source="random-topk"), weights)


def identity_sae(d_in: int) -> StandardSae:
    """Return a ReLU SAE that reconstructs every row exactly: latents [relu(x), relu(-x)], one latent that
    never fires (bias -1, no weights) and one that always fires (bias +1) but decodes to nothing."""
    eye = torch.eye(d_in)
    zero_column = torch.zeros(d_in, 1)
    weights = {
        "W_enc": torch.cat([eye, -eye, zero_column, zero_column], dim=1),
        "b_enc": torch.cat([torch.zeros(2 * d_in), torch.tensor([-1.0, 1.0])]),
        "W_dec": torch.cat([eye, -eye, torch.zeros(2, d_in)]),
        "b_dec": torch.zeros(d_in),
    }
    cfg = SaeConfig(d_in=d_in, d_sae=2 * d_in + 2, architecture="standard", apply_b_dec_to_input=False,
                    source="identity")
    return StandardSae(cfg, weights)


def mean_sae(rows: torch.Tensor) -> StandardSae:
    """Return an SAE whose latents never fire and whose reconstruction is the rows' mean (b_dec)."""
    d_in = rows.shape[1]
    weights = {"W_enc": torch.zeros(d_in, 4), "b_enc": -torch.ones(4), "W_dec": torch.zeros(4, d_in),
               "b_dec": rows.double().mean(dim=0).float()}
    cfg = SaeConfig(d_in=d_in, d_sae=4, architecture="standard", apply_b_dec_to_input=False, source="mean")
    return StandardSae(cfg, weights)


def random_rows(count: int, width: int, seed: int = 0, offset: float = 0.0) -> torch.Tensor:
    generator = torch.Generator().manual_seed(seed)
    return torch.randn(count, width, generator=generator) * torch.linspace(0.5, 2.0, width) + offset


def uneven_batches(rows: torch.Tensor) -> list[torch.Tensor]:
    return list(rows.split([7, 64, 1, 100, rows.shape[0] - 172]))


# ----------------------------------------------------------------------------- row metrics


def test_row_metrics_equal_the_naive_formulas_on_all_rows_at_once():
    rows = random_rows(300, 32, offset=50.0)  # a common offset, as residual streams have
    saes = {"a": topk_sae(32, seed=1), "b": topk_sae(32, d_sae=128, k=3, seed=2)}
    # (rows, columns) pairs from a function, as RowSource.sequential yields them
    found = row_fidelity(saes, lambda: ((batch, {"index": None}) for batch in uneven_batches(rows)))
    x = rows.double()
    for name, sae in saes.items():
        reconstruction, latents = sae.reconstruct(rows)
        fired = latents != 0
        frequency = fired.double().mean(dim=0)
        result = found[name]
        expected_fvu = float((x - reconstruction.double()).square().sum() / (x - x.mean(dim=0)).square().sum())
        assert result.rows == 300 and result.d_sae == sae.cfg.d_sae
        assert result.fvu == pytest.approx(expected_fvu, rel=1e-9)
        assert result.l0 == pytest.approx(float(fired.sum(dim=1).double().mean()), rel=1e-12)
        assert result.dead == int((frequency == 0).sum())
        assert result.dense == int((frequency > 0.1).sum())
        assert sum(result.firing_histogram) == sae.cfg.d_sae - result.dead
    assert found["b"].l0 == 3.0  # TopK: exactly k latents per row (pre-activations are positive somewhere)


def test_exact_and_mean_reconstructions_give_fvu_zero_and_one_with_the_planted_latents():
    rows = random_rows(250, 16, seed=3, offset=-2.0)  # some coordinates are never positive
    found = row_fidelity({"identity": identity_sae(16), "mean": mean_sae(rows)}, uneven_batches(rows))
    identity = found["identity"]
    assert identity.fvu == 0.0
    assert identity.l0 == 16 + 1  # every coordinate is non-zero on one side, plus the always-on latent
    # latent j fires where coordinate j > 0, latent 16 + j where it is < 0; the planted ones never / always
    signed = torch.cat([(rows > 0).double().mean(dim=0), (rows < 0).double().mean(dim=0)])
    assert 0 < int((signed == 0).sum()) < 16
    assert identity.dead == int((signed == 0).sum()) + 1
    assert identity.dense == int((signed > 0.1).sum()) + 1
    mean = found["mean"]
    assert mean.fvu == pytest.approx(1.0, abs=1e-6)
    assert (mean.l0, mean.dead, mean.dense) == (0.0, 4, 0)


def test_bad_rows_are_one_line_errors_naming_them():
    sae = topk_sae(32)
    with pytest.raises(ValueError, match=r"^held-out rows: a batch is \(4, 31\), expected \(rows, d_in\) with d_in "
                                         r"\[32\] \(SAEs: \{'a': 32\}\); judge each SAE on its own layer's rows$"):
        row_fidelity({"a": sae}, [torch.zeros(4, 31)])
    bad = random_rows(10, 32)
    bad[6, 3] = float("nan")
    with pytest.raises(ValueError, match=r"^layer 3: rows 5..14 hold NaN or Inf; re-capture the run$"):
        row_fidelity({"a": sae}, [random_rows(5, 32), bad], where="layer 3")
    with pytest.raises(ValueError, match=r"^held-out rows: no rows; hold out episodes that the run captured$"):
        row_fidelity({"a": sae}, iter([torch.zeros(0, 32)]))


# ----------------------------------------------------------------------------- the policy splice


@pytest.fixture(scope="module")
def tokenizer(tmp_path_factory):
    return PromptTokenizer(write_tokenizer(tmp_path_factory.mktemp("tok") / "tokenizer.model"), max_len=MAX_LEN)


@pytest.fixture(scope="module")
def policy(tmp_path_factory):
    checkpoint = write_pi05_checkpoint(tmp_path_factory.mktemp("pi05") / "ckpt", ARCH, seed=4)
    return Pi05Policy.from_checkpoint(checkpoint, ARCH, device="cpu")


@pytest.fixture(scope="module")
def batch(tokenizer):
    return make_batch(ARCH, tokenizer)


@pytest.fixture(scope="module")
def noise():
    return torch.randn(3, 10, 32, generator=torch.Generator().manual_seed(5))


def instruction(batch):
    mask = batch.token_mask.clone()
    mask[:, 0] = False  # not BOS
    return mask


def vector(seed):
    return torch.randn(ARCH.width, generator=torch.Generator().manual_seed(seed))


def test_identity_splice_is_bit_identical_and_an_additive_splice_equals_steering(policy, batch, noise):
    plain = policy.sample_actions(*batch.args(), noise=noise, num_steps=3)
    same = policy.sample_actions(*batch.args(), noise=noise, num_steps=3, splice=Splice(1, lambda rows: rows))
    assert torch.equal(same, plain)
    v, w, mask = vector(1), vector(2), instruction(batch)
    added = policy.sample_actions(*batch.args(), noise=noise, num_steps=3,
                                  splice=Splice(2, lambda rows: rows + v, token_mask=mask))
    steered = policy.sample_actions(*batch.args(), noise=noise, num_steps=3, steering=Steering(2, v, token_mask=mask))
    torch.testing.assert_close(added, steered, rtol=1e-5, atol=1e-5)
    assert (added - plain).abs().max() > 1e-2
    # with a shallower steering the splice runs in the deeper half of the prefix; a deeper one, the shared half
    for low, high in ((0, 2), (2, 1)):
        both = policy.sample_actions(*batch.args(), noise=noise, num_steps=3, steering=Steering(low, w),
                                     splice=Splice(high, lambda rows: rows + v, token_mask=mask))
        expected = policy.sample_actions(*batch.args(), noise=noise, num_steps=3,
                                         steering=[Steering(low, w), Steering(high, v, token_mask=mask)])
        torch.testing.assert_close(both, expected, rtol=1e-5, atol=1e-5)


def test_splice_receives_the_layer_residuals_at_the_chosen_positions_in_order(policy, batch, noise):
    mask = instruction(batch)
    seen = []
    policy.sample_actions(*batch.args(), noise=noise, num_steps=2,
                          splice=Splice(1, lambda rows: seen.append(rows.clone()) or rows, token_mask=mask))
    residuals = policy.prefix.residuals(*batch.args(), [1])[1]  # (B, prefix, width), images first
    where = torch.cat([torch.zeros(3, 3 * ARCH.tokens_per_image, dtype=torch.bool), mask], dim=1)
    assert len(seen) == 1 and seen[0].dtype == torch.float32
    torch.testing.assert_close(seen[0], residuals[where], rtol=1e-6, atol=1e-6)
    assert seen[0].shape == (int(mask.sum()), ARCH.width)


def test_bad_splice_is_one_line_error(policy, batch, noise):
    last = ARCH.depth - 1
    with pytest.raises(ValueError, match=rf"^splice \(lm layer {last}\): the last language-model layer's output only "
                                         rf"feeds the final norm, .*; splice a layer below {last}; token_mask is "
                                         r"\(3, 5\), expected \(3, 32\)$"):
        policy.sample_actions(*batch.args(), noise=noise, splice=Splice(last, zero_ablation,
                                                                        torch.ones(3, 5, dtype=torch.bool)))
    with pytest.raises(ValueError, match=r"^splice \(lm layer 1\): replace returned \(2, 64\), expected \(\d+, 64\) "
                                         r"\(one row per selected position\)$"):
        policy.sample_actions(*batch.args(), noise=noise, splice=Splice(1, lambda rows: rows[:2]))
    with pytest.raises(ValueError, match=r"^Splice: layer -1 must be a non-negative integer; replace must be a "
                                         r"function of the rows, found Tensor$"):
        Splice(-1, torch.zeros(3))


# ----------------------------------------------------------------------------- the action change


FRAMES = [EvalFrame("positive", 0, 3, 3), EvalFrame("positive", 1, 0, 20), EvalFrame("negative", 4, 2, 52),
          EvalFrame("negative", 4, 5, 55), EvalFrame("positive", 1, 7, 27)]


def load(frames):
    """Return cameras of the frames (each frame's pixels seeded by its index), right wrist masked."""
    side = ARCH.image_size
    per_frame = [torch.rand(3, 3, side, side, generator=torch.Generator().manual_seed(f.index)) * 2 - 1
                 for f in frames]
    images = [torch.stack([cameras[slot] for cameras in per_frame]) for slot in range(3)]
    masks = [torch.ones(len(frames), dtype=torch.bool)] * 2 + [torch.zeros(len(frames), dtype=torch.bool)]
    return {"images": images, "image_masks": masks}


def by_hand_delta(policy, prompts, replace, layer, num_steps):
    """Return the mean over frames of ‖Δ robot actions / std‖, each frame run alone."""
    std = torch.tensor(policy.normalization.stats["actions"].std[:7], dtype=torch.float64)
    total = 0.0
    for frame in FRAMES:
        inputs, prompt = load([frame]), prompts.prompts[frame.side]
        noise = frame_noise(frame, 0, 0, 10, 32)[None]
        run = lambda splice: torch.from_numpy(policy.robot_actions(policy.sample_actions(  # noqa: E731
            inputs["images"], inputs["image_masks"], prompt.tokens, prompt.token_mask, noise=noise,
            num_steps=num_steps, splice=splice))).double() / std
        changed = run(Splice(layer, replace, token_mask=prompt.instruction_mask))
        total += float((changed - run(None)).norm())
    return total / len(FRAMES)


def test_identity_recovers_everything_zero_nothing_and_a_partial_splice_matches_by_hand(policy, tokenizer):
    prompts = task_prompts(tokenizer, POSITIVE, NEGATIVE)
    found = action_fidelity(policy, 1, {"identity": lambda rows: rows, "zero": zero_ablation,
                                        "half": lambda rows: 0.5 * rows}, FRAMES, load, prompts, num_steps=3,
                            batch_size=2)
    identity, zero, half = found["identity"], found["zero"], found["half"]
    assert identity.delta_recon == 0.0 and identity.recovered == 1.0
    assert zero.delta_recon == zero.delta_zero > 0.01 and zero.recovered == 0.0
    assert half.delta_zero == zero.delta_zero and all(r.frames == 5 for r in found.values())
    assert half.delta_recon == pytest.approx(by_hand_delta(policy, prompts, lambda rows: 0.5 * rows, 1, 3), rel=1e-4)
    assert half.delta_zero == pytest.approx(by_hand_delta(policy, prompts, zero_ablation, 1, 3), rel=1e-4)
    assert half.recovered == pytest.approx(1 - half.delta_recon / half.delta_zero, rel=1e-12)


# ----------------------------------------------------------------------------- the report


def test_judge_layer_writes_the_table_the_plot_and_the_verdict(policy, tokenizer, tmp_path):
    rows = random_rows(400, ARCH.width, seed=7, offset=1.0)
    trained, borrowed = identity_sae(ARCH.width), topk_sae(ARCH.width, d_sae=128, k=4, seed=8)
    calls = []
    inputs = ActionInputs(policy, FRAMES, load, task_prompts(tokenizer, POSITIVE, NEGATIVE), num_steps=2,
                          batch_size=5)
    out = judge_layer(tmp_path / "layer01", 1, trained, lambda: iter(rows.split(128)), borrowed=borrowed,
                      actions=inputs, progress=lambda done, total: calls.append((done, total)))
    assert sorted(p.name for p in out.iterdir()) == ["fidelity.json", "fidelity.md", "fidelity.png"]
    record = json.loads((out / "fidelity.json").read_text())
    expected = row_fidelity({"borrowed": borrowed}, [rows])["borrowed"]
    assert record["saes"]["borrowed"]["rows"] == expected.as_json()
    assert record["saes"]["trained"]["rows"]["fvu"] == 0.0
    assert record["saes"]["trained"]["actions"]["recovered"] == 1.0  # the exact reconstruction changes nothing
    assert record["saes"]["borrowed"]["actions"]["recovered"] < 1.0
    assert calls[-1] == (4, 4)  # one batch: unchanged, zeroed, trained, borrowed
    assert record["verdict"] == (f"trained reconstructs better: FVU 0.000 trained vs {expected.fvu:.3f} borrowed; "
                                 f"actions recovered 1.000 trained vs "
                                 f"{record['saes']['borrowed']['actions']['recovered']:.3f} borrowed")
    markdown = (out / "fidelity.md").read_text().splitlines()
    assert f"**{record['verdict']}**" in markdown
    header = markdown.index("| " + " | ".join(TABLE_HEADER) + " |")
    assert markdown[header] == "| SAE | rows | FVU | L0 | dead | dense | Δ_recon | Δ_zero | recovered |"
    assert markdown[header + 2].startswith("| trained (identity) | 400 | 0.000 | 65.0 | 1 / 130 | ")
    assert markdown[header + 3].startswith("| borrowed (random-topk) | 400 | ")
    from PIL import Image

    image = np.asarray(Image.open(out / "fidelity.png").convert("RGB"))
    assert image.shape[1] > 800 and len(np.unique(image.reshape(-1, 3), axis=0)) > 20  # drawn, not blank


def test_judge_layer_without_a_borrowed_sae_or_a_policy(tmp_path):
    rows = random_rows(50, 16, seed=9)
    out = judge_layer(tmp_path / "layer05", 5, topk_sae(16, d_sae=32, k=2), [rows])
    record = json.loads((out / "fidelity.json").read_text())
    assert record["actions"] is None and list(record["saes"]) == ["trained"]
    assert record["verdict"] == f"trained SAE: FVU {record['saes']['trained']['rows']['fvu']:.3f}; no borrowed SAE " \
                                "to compare"
    markdown = (out / "fidelity.md").read_text()
    assert "| — | — | — |" in markdown and "Action change not measured (no policy given)." in markdown


def test_judge_layer_keeps_a_folder_with_the_same_identity(tmp_path):
    def rows():
        yield random_rows(50, 16, seed=9)

    def unreadable():
        raise AssertionError("the rows were read again")
        yield

    sae = topk_sae(16, d_sae=32, k=2)
    out = judge_layer(tmp_path / "layer05", 5, sae, rows, identity="a")
    written = (out / "fidelity.json").read_bytes()
    assert json.loads(written)["identity"] == "a"
    assert judge_layer(out, 5, sae, unreadable, identity="a") == out
    assert (out / "fidelity.json").read_bytes() == written
    judge_layer(out, 5, topk_sae(16, d_sae=32, k=2, seed=4), rows, identity="b")
    assert json.loads((out / "fidelity.json").read_text())["identity"] == "b"


def test_verdict_names_the_sae_with_the_lower_fvu():
    def fit(fvu):
        return RowFidelity(rows=10, fvu=fvu, l0=4.0, dead=0, dense=1, d_sae=8, firing_histogram=[])

    def change(recovered):
        return ActionFidelity(frames=3, delta_recon=0.1, delta_zero=0.2, recovered=recovered)

    assert verdict({"trained": fit(0.4), "borrowed": fit(0.0512)}, {}) == \
        "borrowed reconstructs better: FVU 0.400 trained vs 0.051 borrowed"
    assert verdict({"trained": fit(0.05), "borrowed": fit(0.4)}, {"trained": change(0.9), "borrowed": change(None)}) \
        == "trained reconstructs better: FVU 0.050 trained vs 0.400 borrowed; actions recovered 0.900 trained vs " \
           "— borrowed"
    assert verdict({"trained": fit(0.2), "borrowed": fit(0.2)}, {}) == \
        "trained and borrowed reconstruct equally well: FVU 0.200"
