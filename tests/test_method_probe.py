"""Method `probe`: the logistic regression against scikit-learn, the episode-grouped choice of C and its held-out
figures, the default and given C, the method through the registry, and bad input."""

from __future__ import annotations

import json
import logging
import math
from pathlib import Path

import numpy as np
import pytest
import torch
from safetensors.torch import save_file
from sklearn.linear_model import LogisticRegression
from sklearn.metrics import roc_auc_score

from steering_core.vectors.concept_stats import ConceptStats
from steering_core.vectors.directions import SteeringSettings
from steering_core.vectors.methods import METHODS, PairData, probe
from steering_core.vectors.methods.probe import C_GRID, episode_folds, fit_logistic, fit_probe, roc_auc
from steering_core.vectors.methods.registry import SliceRows

PAIR, LAYER = "open_vs_close", 12


def two_concepts(rows: int, width: int, shift: float, seed: int = 0, dtype=torch.float64
                 ) -> tuple[torch.Tensor, torch.Tensor]:
    """Return (positive, negative) rows: anisotropic Gaussians with a common offset, apart by `shift` on axis 0
    (of standard deviation 1; the others' range from 0.1 to 10)."""
    g = torch.Generator().manual_seed(seed)
    scale = torch.logspace(-1, 1, width, dtype=torch.float64).roll(width // 2)
    offset = torch.randn(width, generator=g, dtype=torch.float64) * 5
    pos = torch.randn(rows, width, generator=g, dtype=torch.float64) * scale + offset
    neg = torch.randn(rows, width, generator=g, dtype=torch.float64) * scale + offset
    pos[:, 0] += shift
    return pos.to(dtype), neg.to(dtype)


def sklearn_fit(pos: torch.Tensor, neg: torch.Tensor, c: float) -> LogisticRegression:
    x = torch.cat([pos, neg]).double().numpy()
    y = np.r_[np.ones(len(pos)), np.zeros(len(neg))]
    return LogisticRegression(C=c, tol=1e-10, max_iter=10_000).fit(x, y)


def relative(ours: torch.Tensor | float, theirs: np.ndarray | float) -> float:
    theirs = torch.as_tensor(np.asarray(theirs, dtype=np.float64))
    ours = torch.as_tensor(ours, dtype=torch.float64)
    return float((ours - theirs).norm() / theirs.norm())


def episodes_of(rows: int, episodes: int, first: int) -> torch.Tensor:
    """Return (rows,) episode ids first..first+episodes−1, in blocks."""
    return torch.arange(first, first + episodes).repeat_interleave(math.ceil(rows / episodes))[:rows]


@pytest.mark.parametrize(("c", "dtype"), [(1e-3, torch.float64), (0.1, torch.float64), (1.0, torch.float64),
                                          (100.0, torch.float64), (1.0, torch.float32)])
def test_fit_logistic_matches_scikit_learn_on_overlapping_concepts(c, dtype):
    pos, neg = two_concepts(100, 16, shift=1.0, dtype=dtype)
    w, b, info = fit_logistic(pos, neg, c)
    reference = sklearn_fit(pos, neg, c)
    assert info["converged"] and info["stopped"] == "tolerance"
    assert relative(w, reference.coef_[0]) < 1e-4
    assert relative(b, reference.intercept_[0]) < 1e-4


@pytest.mark.parametrize("c", [1e-3, 1e-2])
def test_fit_logistic_matches_scikit_learn_on_separable_concepts_at_a_small_c(c):
    pos, neg = two_concepts(100, 16, shift=20.0, seed=1)
    assert pos[:, 0].min() > neg[:, 0].max()  # separable: only the penalty keeps w finite
    w, b, info = fit_logistic(pos, neg, c)
    reference = sklearn_fit(pos, neg, c)
    assert info["converged"]
    assert relative(w, reference.coef_[0]) < 1e-4
    assert relative(b, reference.intercept_[0]) < 1e-4


def test_folds_keep_each_episode_whole_and_every_fold_holds_both_concepts():
    g = torch.Generator().manual_seed(2)
    for k, pos_ids, neg_ids in ((5, range(0, 7), range(100, 109)),   # disjoint episodes
                                (3, range(0, 6), range(3, 12)),      # episodes 3..5 hold both concepts
                                (2, range(0, 4), (1, 3))):           # the smaller side's episodes all shared
        pos_ep = torch.tensor(pos_ids)[torch.randint(len(pos_ids), (80,), generator=g)]
        neg_ep = torch.tensor(neg_ids)[torch.randint(len(neg_ids), (60,), generator=g)]
        pos_ep[:len(pos_ids)], neg_ep[:len(neg_ids)] = torch.tensor(pos_ids), torch.tensor(neg_ids)
        pos_fold, neg_fold = episode_folds(pos_ep, neg_ep, k)
        fold_of: dict[int, set[int]] = {}
        for episode, fold in zip(torch.cat([pos_ep, neg_ep]).tolist(), torch.cat([pos_fold, neg_fold]).tolist()):
            fold_of.setdefault(episode, set()).add(fold)
        assert all(len(folds) == 1 for folds in fold_of.values())  # held-out folds are episode-disjoint
        assert set(pos_fold.tolist()) == set(neg_fold.tolist()) == set(range(k))
        again = episode_folds(pos_ep, neg_ep, k)
        assert torch.equal(again[0], pos_fold) and torch.equal(again[1], neg_fold)


def test_cross_validation_picks_the_c_of_the_lowest_held_out_log_loss_as_scikit_learn_scores_it():
    pos, neg = two_concepts(120, 8, shift=2.5, seed=3)
    pos_ep, neg_ep = episodes_of(120, 6, 0), episodes_of(120, 6, 50)
    fit = fit_probe(pos, neg, pos_ep, neg_ep, folds=5, c=None)
    assert fit.folds == 5 and fit.c_grid == C_GRID and fit.c == C_GRID[int(np.argmin(fit.cv_log_loss))]
    assert fit.c_choice.startswith("cross-validation") and fit.cv_skipped is None and fit.cv_unconverged == 0
    # each C's mean held-out log-loss, refitted fold by fold with scikit-learn on the same folds
    folds = torch.cat(episode_folds(pos_ep, neg_ep, 5)).numpy()
    x, y = torch.cat([pos, neg]).numpy(), np.r_[np.ones(120), np.zeros(120)]
    for c, ours in zip(C_GRID, fit.cv_log_loss):
        losses = []
        for f in range(5):
            model = LogisticRegression(C=c, tol=1e-10, max_iter=10_000).fit(x[folds != f], y[folds != f])
            p = np.clip(model.predict_proba(x[folds == f])[:, 1], 1e-300, 1 - 1e-16)
            losses.append(-np.mean(y[folds == f] * np.log(p) + (1 - y[folds == f]) * np.log1p(-p)))
        assert ours == pytest.approx(np.mean(losses), rel=1e-4)
    labels = np.r_[np.ones(120), np.zeros(120)]
    assert fit.heldout_auc == pytest.approx(roc_auc_score(labels, fit.heldout_scores.numpy()), abs=1e-12)
    assert fit.heldout_accuracy == pytest.approx(np.mean((fit.heldout_scores.numpy() > 0) == labels))
    assert fit.heldout_accuracy > 0.7 and fit.heldout_auc > 0.85 and fit.train_accuracy >= fit.heldout_accuracy
    reference = sklearn_fit(pos, neg, fit.c)  # the refit on all rows at the chosen C
    assert relative(fit.weights, reference.coef_[0]) < 1e-4 and fit.converged


def test_held_out_auc_is_chance_without_a_signal_and_near_one_with_one():
    chance = fit_probe(*two_concepts(200, 12, shift=0.0, seed=4), episodes_of(200, 8, 0), episodes_of(200, 8, 20),
                       folds=4, c=None)
    signal = fit_probe(*two_concepts(200, 12, shift=4.0, seed=4), episodes_of(200, 8, 0), episodes_of(200, 8, 20),
                       folds=4, c=None)
    assert abs(chance.heldout_auc - 0.5) < 0.15
    assert signal.heldout_auc > 0.97 and signal.heldout_accuracy > 0.9


def test_roc_auc_counts_ties_as_one_half():
    scores = torch.tensor([0.1, 0.4, 0.4, 0.8, 0.4, 0.2])
    labels = torch.tensor([False, True, False, True, True, False])
    assert roc_auc(scores, labels) == pytest.approx(roc_auc_score(labels.numpy(), scores.numpy()))


def test_one_episode_per_side_fits_at_the_default_c_without_held_out_figures():
    pos, neg = two_concepts(40, 6, shift=2.0, seed=5)
    fit = fit_probe(pos, neg, torch.zeros(40, dtype=torch.long), torch.ones(40, dtype=torch.long), folds=5, c=None)
    reason = "default: C = 1 (too few training episodes to cross-validate: 1 positive, 1 negative)"
    assert fit.c == 1.0 and fit.c_choice == reason and fit.cv_skipped == reason
    assert fit.heldout_accuracy is None and fit.heldout_auc is None and fit.folds is None and fit.c_grid is None
    assert torch.allclose(fit.weights, fit_logistic(pos, neg, 1.0)[0])
    no_episodes = fit_probe(pos, neg, None, None, folds=5, c=None)
    assert no_episodes.c == 1.0 and "no episodes" in no_episodes.c_choice
    assert no_episodes.record()["episodes"] == {"positive": None, "negative": None}


def test_a_given_c_is_fitted_as_it_is():
    pos, neg = two_concepts(60, 6, shift=1.0, seed=6)
    fit = fit_probe(pos, neg, episodes_of(60, 6, 0), episodes_of(60, 6, 10), folds=5, c=0.5)
    assert fit.c == 0.5 and fit.c_choice == "given (probe_c)" and fit.heldout_auc is None
    assert "not cross-validated" in fit.cv_skipped
    assert relative(fit.weights, sklearn_fit(pos, neg, 0.5).coef_[0]) < 1e-4


def write_slice(path: Path, rows: torch.Tensor, episodes: torch.Tensor | None) -> Path:
    tensors = {"residuals": rows.float().contiguous()}
    if episodes is not None:
        tensors["episode_index"] = episodes.long()
    save_file(tensors, path)
    return path


def pair_data(tmp_path: Path, pos: torch.Tensor, neg: torch.Tensor, pos_ep: torch.Tensor | None = None,
              neg_ep: torch.Tensor | None = None, **settings) -> PairData:
    """Return the PairData of two slices written from the rows (statistics from the rows themselves)."""
    paths = (write_slice(tmp_path / "positive.safetensors", pos, pos_ep),
             write_slice(tmp_path / "negative.safetensors", neg, neg_ep))
    stats = {side: ConceptStats(side, path, len(rows), rows.double().mean(0), None, None, None, None, None)
             for side, path, rows in zip(("positive", "negative"), paths, (pos, neg))}
    options = SteeringSettings(pairs_config=tmp_path / "pairs.json", layer=LAYER, **settings)
    return PairData(PAIR, LAYER, stats, paths, None, options)


def test_the_registered_method_returns_the_probe_weights_and_a_json_record(tmp_path):
    pos, neg = two_concepts(90, 10, shift=1.5, seed=7, dtype=torch.float32)
    pos_ep, neg_ep = episodes_of(90, 3, 0), episodes_of(90, 4, 10)
    assert METHODS["probe"].reads_rows and not METHODS["probe"].needs_sae
    result = METHODS["probe"].compute(pair_data(tmp_path, pos, neg, pos_ep, neg_ep, probe_folds=5))
    fit = fit_probe(pos, neg, pos_ep, neg_ep, folds=5, c=None)
    assert fit.folds == 3  # min(probe_folds, 3 positive episodes, 4 negative)
    assert torch.equal(result.direction, fit.weights.float()) and result.direction.dtype == torch.float32
    assert float(result.direction[0]) > 0  # toward the positive concept
    record = json.loads(json.dumps(result.record))
    assert record["C"] == fit.c and record["folds"] == 3 and len(record["cv_log_loss"]) == len(C_GRID)
    assert record["rows"] == {"positive": 90, "negative": 90} and record["episodes"] == {"positive": 3, "negative": 4}
    assert record["converged"] and record["heldout_auc"] == fit.heldout_auc
    given = METHODS["probe"].compute(pair_data(tmp_path, pos, neg, pos_ep, neg_ep, probe_c=0.2))
    assert given.record["C"] == 0.2 and given.record["C_choice"] == "given (probe_c)"


def test_a_fit_at_the_iteration_cap_is_returned_unconverged_with_a_warning(tmp_path, monkeypatch, caplog):
    pos, neg = two_concepts(60, 8, shift=1.0, seed=8, dtype=torch.float32)
    info = fit_logistic(pos, neg, 1.0, max_iter=1)[2]
    assert info["iterations"] == 1 and not info["converged"] and info["stopped"] == "iteration cap"
    monkeypatch.setattr(probe, "MAX_ITER", 1)
    with caplog.at_level(logging.WARNING, logger=probe.__name__):
        result = METHODS["probe"].compute(pair_data(tmp_path, pos, neg, probe_c=1.0))
    assert result.record["converged"] is False and result.record["stopped"] == "iteration cap"
    assert result.direction.abs().sum() > 0
    assert f"pair {PAIR!r}, layer {LAYER}" in caplog.text and "iteration cap" in caplog.text


def one_line_error(data: PairData, *fragments: str) -> None:
    with pytest.raises(ValueError) as raised:
        METHODS["probe"].compute(data)
    message = str(raised.value)
    assert "\n" not in message and f"pair {PAIR!r}, layer {LAYER}, steering.methods `probe`" in message
    assert all(fragment in message for fragment in fragments), message


def test_rows_of_one_concept_only_are_refused(tmp_path):
    pos, neg = two_concepts(30, 6, shift=1.0, seed=9, dtype=torch.float32)
    one_line_error(pair_data(tmp_path, pos, neg[:0]), "negative training slice holds (0, 6) rows")
    one_line_error(pair_data(tmp_path, pos, pos.clone()), "positive and negative training rows are the same")
    same = pair_data(tmp_path, pos, neg)
    same = PairData(PAIR, LAYER, same.stats, (same.slices[0], same.slices[0]), None, same.settings)
    one_line_error(same, "the same")
    one_line_error(pair_data(tmp_path, pos[:1].repeat(3, 1), pos[:1].repeat(2, 1)), "weights are all zero")
    one_line_error(pair_data(tmp_path, pos, neg[:, :5]), "6 wide", "negative rows 5")


def test_non_finite_rows_and_mismatched_episodes_are_refused(tmp_path):
    pos, neg = two_concepts(30, 6, shift=1.0, seed=10, dtype=torch.float32)
    data = pair_data(tmp_path, pos, neg)
    bad = pos.clone()
    bad[3, 2] = float("nan")
    data._rows["positive"] = SliceRows(bad, None)  # past the slice reader's own check
    one_line_error(data, "positive training rows hold NaN or inf")
    one_line_error(pair_data(tmp_path, pos, neg, episodes_of(29, 3, 0), episodes_of(30, 3, 5)),
                   "29 episode_index values for 30 rows")
