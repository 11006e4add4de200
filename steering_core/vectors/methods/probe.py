"""`probe`: an L2-regularised logistic regression between the concepts' training rows; its weights are the direction.

The objective is scikit-learn's `LogisticRegression(penalty="l2", C=C, fit_intercept=True)`: minimise
½‖w‖² + C·Σᵢ log(1 + exp(−yᵢ(w·xᵢ + b))) over the rows as they are (no standardisation: w lives in the residual
space; the intercept is not penalised). It is solved in torch, divided by C·rows (the same optimum), by L-BFGS:
parameters in float64, the rows in float32 (float64 rows stay float64) and centred on their mean (the intercept
absorbs the shift), every step preconditioned by the Hessian at w = 0, M = Σ/4 + λI (Σ the rows' covariance from at
most `GRAM_ROWS` of them, λ = 1/(C·rows)), so that a fit takes tens of iterations whatever the residuals' scales.
The line search backtracks to Armijo's condition or, where float32 rows blur the objective's last digits, to the
approximate Wolfe conditions of Hager and Zhang (the gradient stays exact far longer than the objective).
The cross-validation's fits, every (fold, C) of the grid, share each pass over the rows as the rows of one batch,
each with its own L-BFGS history and step.

C is `probe_c` when given; otherwise the C of `C_GRID` with the lowest mean held-out log-loss over folds of whole
episodes, then refitted on all rows; `DEFAULT_C` when a concept has fewer than two training episodes.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any

import torch
import torch.nn.functional as F

from steering_core.vectors.methods.registry import MethodResult, PairData, register_method

logger = logging.getLogger(__name__)

C_GRID = tuple(float(c) for c in torch.logspace(-4, 4, 10, dtype=torch.float64))  # LogisticRegressionCV's Cs=10
DEFAULT_C = 1.0
MAX_ITER = 500        # L-BFGS iterations of the fit on all rows
CV_MAX_ITER = 100     # of each cross-validation fit (LogisticRegressionCV's max_iter)
TOLERANCE = 1e-5      # on the preconditioned gradient norm √(gᵀM⁻¹g), about √(2·(f − f*)) in mean log-loss units;
                      # float32 rows of 100,000 x 2048 reach about 3e-7
HISTORY = 10          # L-BFGS correction pairs
HALVINGS = 10         # line-search halvings before a fit stops at the rows' float precision (no decrease left)
STOPS = ("tolerance", "float precision", "iteration cap")  # why a fit stopped; converged unless at the cap
GRAM_ROWS = 16_384


@dataclass(frozen=True)
class ProbeFit:
    """A fitted probe: (width,) float64 weights toward the positive concept, its intercept and how C was chosen."""

    weights: torch.Tensor
    intercept: float
    c: float
    c_choice: str
    c_grid: tuple[float, ...] | None        # the cross-validated grid and each C's mean held-out log-loss
    cv_log_loss: tuple[float, ...] | None
    folds: int | None
    cv_unconverged: int | None              # cross-validation fits stopped at the iteration cap
    heldout_accuracy: float | None          # out-of-fold, pooled over folds, at the chosen C
    heldout_auc: float | None
    cv_skipped: str | None                  # why there are no held-out figures
    heldout_scores: torch.Tensor | None     # (rows,) out-of-fold w·x + b, positive rows first
    train_accuracy: float
    rows: tuple[int, int]                   # (positive, negative)
    episodes: tuple[int | None, int | None]
    iterations: int
    converged: bool
    stopped: str                            # one of `STOPS`
    gradient_norm: float                    # the final fit's √(gᵀM⁻¹g)

    def record(self) -> dict[str, Any]:
        """Return the JSON record of the fit (the held-out scores left out)."""
        return {
            "C": self.c, "C_choice": self.c_choice,
            "C_grid": list(self.c_grid) if self.c_grid else None,
            "cv_log_loss": list(self.cv_log_loss) if self.cv_log_loss else None,
            "folds": self.folds, "cv_unconverged": self.cv_unconverged,
            "heldout_accuracy": self.heldout_accuracy, "heldout_auc": self.heldout_auc, "cv_skipped": self.cv_skipped,
            "train_accuracy": self.train_accuracy,
            "rows": dict(zip(("positive", "negative"), self.rows)),
            "episodes": dict(zip(("positive", "negative"), self.episodes)),
            "intercept": self.intercept, "iterations": self.iterations, "converged": self.converged,
            "stopped": self.stopped, "gradient_norm": self.gradient_norm,
        }


class _Rows:
    """Both concepts' rows, centred on their mean (the intercept absorbs the shift), with labels ±1, each row's fold,
    and the eigenvectors and eigenvalues of their covariance (from at most `GRAM_ROWS` rows): what fits share."""

    def __init__(self, x_pos: torch.Tensor, x_neg: torch.Tensor, fold: torch.Tensor) -> None:
        dtype = torch.float64 if x_pos.dtype == x_neg.dtype == torch.float64 else torch.float32
        self.x = torch.empty(len(x_pos) + len(x_neg), x_pos.shape[1], dtype=dtype)
        self.x[:len(x_pos)], self.x[len(x_pos):] = x_pos, x_neg
        self.mean = sum(block.sum(0, dtype=torch.float64) for block in self.x.split(GRAM_ROWS)) / len(self.x)
        self.x -= self.mean.to(dtype)
        self.y = torch.cat([torch.ones(len(x_pos)), -torch.ones(len(x_neg))]).double()
        self.fold = fold
        sample = self.x[::-(-len(self.x) // GRAM_ROWS)].double()  # every row, or evenly strided ones
        variances, self.basis = torch.linalg.eigh(sample.T @ sample / len(sample))
        self.variances = variances.clamp_min(0)

    def scores(self, v: torch.Tensor) -> torch.Tensor:
        """Return the (rows, k) decision values of parameters v (k, width + 1) on the centred rows."""
        return (self.x @ v[:, :-1].to(self.x.dtype).T).double() + v[:, -1]

    def intercepts(self, v: torch.Tensor) -> torch.Tensor:
        """Return the (k,) intercepts of parameters v on the rows as they are (not centred)."""
        return v[:, -1] - v[:, :-1] @ self.mean


class _Fits:
    """L-BFGS fits sharing every pass over the rows: fit j fits the rows whose fold is not `held[j]` (−1: all rows)
    at C = `cs[j]`. Parameters are (fits, width + 1) float64, the intercept last."""

    def __init__(self, rows: _Rows, held: torch.Tensor, cs: torch.Tensor) -> None:
        self.rows, self.held = rows, held
        self.count = (rows.fold[:, None] != held[None]).sum(0).double()
        self.lam = 1.0 / (cs * self.count)
        self.inverse_curvature = 1 / (rows.variances[None] / 4 + self.lam[:, None])  # (fits, width)

    def evaluate(self, fits: torch.Tensor, v: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Return the objectives (k,) and gradients (k, width + 1) of `fits` at their parameters v."""
        x, y, w = self.rows.x, self.rows.y[:, None], v[:, :-1]
        margin = y * self.rows.scores(v)
        mask = self.rows.fold[:, None] != self.held[fits][None]
        f = (F.softplus(-margin) * mask).sum(0) / self.count[fits] + 0.5 * self.lam[fits] * w.square().sum(1)
        r = (-y * torch.sigmoid(-margin) * mask / self.count[fits]).T
        return f, torch.cat([(r.to(x.dtype) @ x).double() + self.lam[fits, None] * w, r.sum(1, keepdim=True)], 1)

    def precondition(self, q: torch.Tensor, fits: torch.Tensor) -> torch.Tensor:
        """Return M⁻¹q for `fits`: M = Σ/4 + λI for the weights, 1/4 for the intercept."""
        basis = self.rows.basis
        return torch.cat([(q[:, :-1] @ basis) * self.inverse_curvature[fits] @ basis.T, 4 * q[:, -1:]], 1)

    def run(self, max_iter: int, tol: float = TOLERANCE
            ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """Run every fit from w = 0 and the intercept at its rows' log odds; return the parameters and, per fit,
        the iterations, why it stopped (an index of `STOPS`) and its final gradient norm √(gᵀM⁻¹g)."""
        m, every = len(self.held), torch.arange(len(self.held))
        positives = ((self.rows.y[:, None] > 0) & (self.rows.fold[:, None] != self.held[None])).sum(0)
        v = torch.zeros(m, self.rows.x.shape[1] + 1, dtype=torch.float64)
        v[:, -1] = torch.log(positives / (self.count - positives))
        f, g = self.evaluate(every, v)
        history_s = torch.zeros(HISTORY, *v.shape, dtype=torch.float64)
        history_y, rho = torch.zeros_like(history_s), torch.zeros(HISTORY, m, dtype=torch.float64)
        gamma = torch.ones(m, dtype=torch.float64)
        iterations, stalled = torch.zeros(m, dtype=torch.long), torch.zeros(m, dtype=torch.bool)
        for _ in range(max_iter):
            norm = (g * self.precondition(g, every)).sum(1).clamp_min(0).sqrt()
            fits = torch.nonzero((norm > tol) & ~stalled).squeeze(1)
            if not len(fits):
                break
            q, alphas = -g[fits], []
            for i in reversed(range(HISTORY)):  # the two-loop recursion, fit by fit
                alphas.append(rho[i, fits] * (history_s[i, fits] * q).sum(1))
                q -= alphas[-1][:, None] * history_y[i, fits]
            step = gamma[fits, None] * self.precondition(q, fits)
            for i, alpha in zip(range(HISTORY), reversed(alphas)):
                step += (alpha - rho[i, fits] * (history_y[i, fits] * step).sum(1))[:, None] * history_s[i, fits]
            slope = (g[fits] * step).sum(1)
            t = torch.ones(len(fits), dtype=torch.float64)
            new_f, new_g = f[fits].clone(), g[fits].clone()
            pending = torch.arange(len(fits))
            for _ in range(HALVINGS):  # backtracking, fit by fit, to Armijo's or the approximate Wolfe conditions
                trial = v[fits[pending]] + t[pending, None] * step[pending]
                trial_f, trial_g = self.evaluate(fits[pending], trial)
                before = f[fits[pending]]
                ok = (trial_f <= before + 1e-4 * t[pending] * slope[pending]) | (
                    (trial_f <= before + 1e-6 * before.abs())
                    & ((trial_g * step[pending]).sum(1).abs() <= 0.9 * slope[pending].abs()))
                new_f[pending[ok]], new_g[pending[ok]] = trial_f[ok], trial_g[ok]
                pending = pending[~ok]
                if not len(pending):
                    break
                t[pending] /= 2
            moved = torch.ones(len(fits), dtype=torch.bool)
            moved[pending] = False
            stalled[fits[pending]] = True  # no decrease left at the rows' float precision
            s = torch.where(moved, t, 0.0)[:, None] * step
            y = new_g - g[fits]
            sy = (s * y).sum(1)
            curved = moved & (sy > 1e-12 * s.norm(dim=1) * y.norm(dim=1))
            history_s, history_y, rho = history_s.roll(-1, 0), history_y.roll(-1, 0), rho.roll(-1, 0)
            history_s[-1], history_y[-1], rho[-1] = 0.0, 0.0, 0.0
            history_s[-1, fits], history_y[-1, fits] = s, y
            rho[-1, fits] = torch.where(curved, 1 / sy.where(curved, 1.0), 0.0)
            yhy = (y * self.precondition(y, fits)).sum(1)
            gamma[fits] = torch.where(curved, sy / yhy.where(curved, 1.0), gamma[fits])
            v[fits] += s
            f[fits], g[fits] = new_f, new_g
            iterations[fits] += moved.long()
        norm = (g * self.precondition(g, every)).sum(1).clamp_min(0).sqrt()
        stop = torch.where(norm <= tol, 0, torch.where(stalled, 1, 2))
        return v, iterations, stop, norm


def fit_logistic(x_pos: torch.Tensor, x_neg: torch.Tensor, c: float, *, max_iter: int = MAX_ITER,
                 tol: float = TOLERANCE) -> tuple[torch.Tensor, float, dict[str, Any]]:
    """Return the (width,) float64 weights, intercept and {iterations, converged, stopped, gradient_norm} of the
    logistic regression of positive rows (label 1) against negative rows (label 0) at C = `c`."""
    rows = _Rows(x_pos, x_neg, torch.zeros(len(x_pos) + len(x_neg), dtype=torch.long))
    v, iterations, stop, norm = _Fits(rows, torch.tensor([-1]), torch.tensor([float(c)], dtype=torch.float64)
                                      ).run(max_iter, tol)
    return v[0, :-1], float(rows.intercepts(v)[0]), {
        "iterations": int(iterations[0]), "converged": STOPS[stop[0]] != "iteration cap",
        "stopped": STOPS[stop[0]], "gradient_norm": float(norm[0])}


def episode_folds(episodes_pos: torch.Tensor, episodes_neg: torch.Tensor, k: int
                  ) -> tuple[torch.Tensor, torch.Tensor]:
    """Return each row's fold (0..k−1) per side, by episode: the side with fewer episodes has its sorted episode ids
    dealt round-robin, then the other side's episodes not already placed fill the folds it lacks first, then
    round-robin. An episode in both sides is in one fold, and every fold holds episodes of both sides (k at most
    either side's episode count)."""
    ids = [episodes.unique(return_inverse=True) for episodes in (episodes_pos, episodes_neg)]
    first, second = sorted((unique.tolist() for unique, _ in ids), key=len)
    fold_of = {episode: i % k for i, episode in enumerate(first)}
    lacking = sorted(set(range(k)) - {fold_of[episode] for episode in second if episode in fold_of})
    new = [episode for episode in second if episode not in fold_of]
    for i, episode in enumerate(new):
        fold_of[episode] = lacking[i] if i < len(lacking) else (i - len(lacking)) % k
    return tuple(torch.tensor([fold_of[e] for e in unique.tolist()], dtype=torch.long)[inverse]
                 for unique, inverse in ids)


def roc_auc(scores: torch.Tensor, labels: torch.Tensor) -> float:
    """Return the ROC AUC of scores for boolean labels (ties count one half): the Mann–Whitney statistic."""
    _, inverse, counts = torch.unique(scores, return_inverse=True, return_counts=True)
    ranks = (counts.cumsum(0) - (counts - 1) / 2).double()[inverse]
    positives, negatives = int(labels.sum()), int((~labels).sum())
    return float((ranks[labels].sum() - positives * (positives + 1) / 2) / (positives * negatives))


def fit_probe(rows_pos: torch.Tensor, rows_neg: torch.Tensor, episodes_pos: torch.Tensor | None,
              episodes_neg: torch.Tensor | None, *, folds: int, c: float | None) -> ProbeFit:
    """Fit the probe: at C = `c` when given, else at the C of `C_GRID` with the lowest mean held-out log-loss over
    min(`folds`, either side's episodes) folds of whole episodes (`DEFAULT_C` when a side has fewer than two)."""
    episodes = tuple(None if e is None else len(e.unique()) for e in (episodes_pos, episodes_neg))
    k = min(folds, *episodes) if None not in episodes else 0
    labels = torch.cat([torch.ones(len(rows_pos), dtype=torch.bool), torch.zeros(len(rows_neg), dtype=torch.bool)])
    cv: dict[str, Any] = {"c_grid": None, "cv_log_loss": None, "folds": None, "cv_unconverged": None,
                          "heldout_accuracy": None, "heldout_auc": None, "cv_skipped": None, "heldout_scores": None}
    if c is not None or k < 2:
        if c is not None:
            choice, cv["cv_skipped"] = "given (probe_c)", "C given (probe_c): not cross-validated"
        else:
            c = DEFAULT_C
            why = ("the slices record no episodes" if None in episodes else
                   f"too few training episodes to cross-validate: {episodes[0]} positive, {episodes[1]} negative")
            choice = cv["cv_skipped"] = f"default: C = {DEFAULT_C:g} ({why})"
        rows = _Rows(rows_pos, rows_neg, torch.zeros(len(labels), dtype=torch.long))
    else:
        fold = torch.cat(episode_folds(episodes_pos, episodes_neg, k))
        rows = _Rows(rows_pos, rows_neg, fold)
        grid = torch.tensor(C_GRID, dtype=torch.float64)
        v, _, stop, _ = _Fits(rows, torch.arange(k).repeat(len(grid)), grid.repeat_interleave(k)).run(CV_MAX_ITER)
        scores = rows.scores(v).view(len(labels), len(grid), k)
        heldout = scores.gather(2, fold[:, None, None].expand(-1, len(grid), 1)).squeeze(2)  # (rows, C)
        loss = F.softplus(-torch.where(labels, 1.0, -1.0).double()[:, None] * heldout)
        cv_log_loss = torch.stack([loss[fold == f].mean(0) for f in range(k)]).mean(0)
        best = int(torch.argmin(cv_log_loss))  # the first, smaller C of equal losses
        c, choice = C_GRID[best], f"cross-validation: lowest mean held-out log-loss over {k} folds by episode"
        cv |= {"c_grid": C_GRID, "cv_log_loss": tuple(cv_log_loss.tolist()), "folds": k,
               "cv_unconverged": int((stop == STOPS.index("iteration cap")).sum()),
               "heldout_accuracy": float(((heldout[:, best] > 0) == labels).double().mean()),
               "heldout_auc": roc_auc(heldout[:, best], labels), "heldout_scores": heldout[:, best]}
    v, iterations, stop, norm = _Fits(rows, torch.tensor([-1]), torch.tensor([float(c)], dtype=torch.float64)
                                      ).run(MAX_ITER)
    train = rows.scores(v).squeeze(1)
    return ProbeFit(weights=v[0, :-1], intercept=float(rows.intercepts(v)[0]), c=float(c), c_choice=choice,
                    train_accuracy=float(((train > 0) == labels).double().mean()),
                    rows=(len(rows_pos), len(rows_neg)), episodes=episodes, iterations=int(iterations[0]),
                    converged=STOPS[stop[0]] != "iteration cap", stopped=STOPS[stop[0]],
                    gradient_norm=float(norm[0]), **cv)


@register_method("probe", "the weights of an L2 logistic regression between the concepts' training rows "
                          "(C by episode-grouped cross-validation unless probe_c)", reads_rows=True)
def probe_direction(data: PairData) -> MethodResult:
    """Return the probe's weights (toward the positive concept) and its record; ValueError for rows of one concept
    or non-finite rows."""
    where = f"{data.where}, steering.methods `probe`"
    sides = [data.rows(side) for side in ("positive", "negative")]
    for side, rows in zip(("positive", "negative"), sides):
        if rows.rows.ndim != 2 or not len(rows.rows):
            raise ValueError(f"{where}: the {side} training slice holds {tuple(rows.rows.shape)} rows, expected "
                             "(rows > 0, width): the probe needs rows of both concepts")
        if not torch.isfinite(rows.rows).all():
            raise ValueError(f"{where}: the {side} training rows hold NaN or inf, expected finite rows; re-run slice")
        if rows.episodes is not None and rows.episodes.shape != rows.rows.shape[:1]:
            raise ValueError(f"{where}: the {side} slice has {rows.episodes.numel()} episode_index values for "
                             f"{len(rows.rows)} rows, expected one per row; re-run slice")
    positive, negative = sides
    if positive.rows.shape[1] != negative.rows.shape[1]:
        raise ValueError(f"{where}: positive rows are {positive.rows.shape[1]} wide, negative rows "
                         f"{negative.rows.shape[1]}, expected one residual width")
    if torch.equal(positive.rows, negative.rows):
        raise ValueError(f"{where}: the positive and negative training rows are the same "
                         f"({data.slices[0]}, {data.slices[1]}), expected two concepts")
    fit = fit_probe(positive.rows, negative.rows, positive.episodes, negative.episodes,
                    folds=data.settings.probe_folds, c=data.settings.probe_c)
    if not fit.converged:
        logger.warning("%s: the probe at C = %g reached the iteration cap (%d) with gradient %.2g > %g; its "
                       "weights are used as they are (converged: false in the record)", where, fit.c, MAX_ITER,
                       fit.gradient_norm, TOLERANCE)
    if not fit.weights.any():
        raise ValueError(f"{where}: the probe's weights are all zero, expected a direction; the rows do not tell "
                         "the concepts apart")
    return MethodResult(fit.weights.float(), fit.record())
