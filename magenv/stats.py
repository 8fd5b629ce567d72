"""Paired statistics of a method against a reference on the same units (trials, or training seeds).

One function, :func:`paired_ratio`, for every "method vs reference" claim
(``magenv sweep``'s table; ``compare``/``report`` may reuse it). Both score
arrays are errors, lower is better (RMSE in degrees), and entry i of each
comes from the same unit i (the same trial, or the same training seed's
evaluation), which is what pairs them.

* per-unit ratio ``r_i = method_i / reference_i`` (< 1: the method is better);
* point estimate: the geometric mean ``exp(mean(log r_i))``, so that
  swapping method and reference gives exactly the reciprocal (a ratio of 0.5
  and one of 2 cancel, as they should);
* 95 % interval: percentile bootstrap over units, resampling the pairs
  together (``n_boot`` resamples from ``numpy.random.default_rng(seed)``:
  same seed, same interval); the quantiles are taken of the resampled mean
  log ratio, then exponentiated, so the swap maps the interval onto its
  reciprocal too;
* win rate: the fraction of units where the method's error is lower, ties
  counted one half;
* interquartile-mean ratio (rliable's IQM, Agarwal et al. 2021, on the log
  ratios): ``exp`` of the mean of the middle half of the sorted ``log r_i``
  (``⌊n/4⌋`` dropped at each end), with its interval from the same bootstrap
  resamples. A few trials with extreme ratios move it less than the
  geometric mean, so where the two differ, those trials decide the verdict.
  Trimming is symmetric, so the swap gives the reciprocal here too. Below
  four units nothing is dropped, and it equals the geometric mean.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

DEFAULT_BOOT = 10_000
DEFAULT_LEVEL = 0.95
_BOOT_CELLS = 2_000_000  # indices drawn at once


@dataclass(frozen=True)
class PairedRatio:
    """Method against reference over ``n`` paired units.

    Attributes:
        n: number of pairs.
        ratio: geometric mean of the per-unit ratios method/reference (< 1: method better).
        low, high: bootstrap interval of ``ratio`` at ``level`` (NaN when n < 2: one pair has no spread).
        win_rate: fraction of units where the method's error is lower (ties count 1/2), in [0, 1].
        iqm, iqm_low, iqm_high: interquartile-mean ratio and its interval (module docstring; NaN interval when
            n < 2).
        level: the intervals' coverage (0.95).
        worst: the largest per-unit ratio (the method's worst unit relative to the reference).
    """

    n: int
    ratio: float
    low: float
    high: float
    win_rate: float
    iqm: float
    iqm_low: float
    iqm_high: float
    level: float = DEFAULT_LEVEL
    worst: float = float("nan")

    def ratio_text(self, digits: int = 3) -> str:
        """ "ratio [low, high]" with ``digits`` decimals."""
        return f"{self.ratio:.{digits}f} [{self.low:.{digits}f}, {self.high:.{digits}f}]"

    def iqm_text(self, digits: int = 3) -> str:
        """ "iqm [iqm_low, iqm_high]" with ``digits`` decimals."""
        return f"{self.iqm:.{digits}f} [{self.iqm_low:.{digits}f}, {self.iqm_high:.{digits}f}]"


def _scores(name: str, values) -> np.ndarray:
    x = np.asarray(values, dtype=float)
    if x.ndim != 1 or len(x) == 0:
        raise ValueError(f"{name} must be a non-empty 1-D sequence of errors, got shape {x.shape}")
    bad = np.flatnonzero(~np.isfinite(x) | (x <= 0))
    if len(bad):
        raise ValueError(f"{name}: errors must be finite and > 0 for a ratio; entry {bad[0]} is {float(x[bad[0]])!r}")
    return x


def interquartile_mean(x: np.ndarray) -> np.ndarray:
    """Mean of the middle half of ``x`` along its last axis: ``⌊n/4⌋`` values dropped at each end after sorting."""
    n = x.shape[-1]
    k = n // 4
    return np.sort(x, axis=-1)[..., k : n - k].mean(axis=-1)


def resamples(n: int, n_boot: int, seed: int):
    """The bootstrap's resamples of ``n`` units: index arrays of shape (k, n), ``n_boot`` rows in all, drawn
    with replacement from ``numpy.random.default_rng(seed)`` (same seed, same resamples), a block at a time so
    that memory stays bounded for thousands of units. The one resampler of every interval here."""
    rng = np.random.default_rng(seed)
    rows = max(1, _BOOT_CELLS // n)
    for i in range(0, n_boot, rows):
        yield rng.integers(0, n, size=(min(rows, n_boot - i), n))


def _check_boot(n_boot, level) -> None:
    if not (isinstance(n_boot, int) and n_boot >= 1):
        raise ValueError(f"n_boot must be an integer ≥ 1, got {n_boot!r}")
    if not 0 < level < 1:
        raise ValueError(f"level must be in (0, 1), got {level!r}")


def paired_ratio(
    method, reference, n_boot: int = DEFAULT_BOOT, seed: int = 0, level: float = DEFAULT_LEVEL
) -> PairedRatio:
    """The paired ratio of ``method`` to ``reference`` errors (equal-length arrays, entry i of both from unit i),
    its bootstrap interval, the win rate and the interquartile-mean ratio with its interval; see the module
    docstring. Raises ValueError naming the bad input."""
    m, r = _scores("method", method), _scores("reference", reference)
    if len(m) != len(r):
        raise ValueError(f"method and reference must pair unit by unit: {len(m)} errors against {len(r)}")
    _check_boot(n_boot, level)
    log_ratio = np.log(m) - np.log(r)
    n = len(log_ratio)
    win = float(np.mean((m < r) + 0.5 * (m == r)))
    ratio, iqm = float(np.exp(log_ratio.mean())), float(np.exp(interquartile_mean(log_ratio)))
    worst = float(np.exp(log_ratio.max()))
    if n < 2:
        return PairedRatio(n, ratio, float("nan"), float("nan"), win, iqm, float("nan"), float("nan"), level, worst)
    boot, boot_iqm = [], []
    for index in resamples(n, n_boot, seed):
        resample = log_ratio[index]
        boot.append(resample.mean(axis=1))
        boot_iqm.append(interquartile_mean(resample))
    q = [(1 - level) / 2, (1 + level) / 2]
    low, high = np.exp(np.quantile(np.concatenate(boot), q))  # on the log scale: swap-symmetric
    iqm_low, iqm_high = np.exp(np.quantile(np.concatenate(boot_iqm), q))
    return PairedRatio(n, ratio, float(low), float(high), win, iqm, float(iqm_low), float(iqm_high), level, worst)


@dataclass(frozen=True)
class Normalised:
    """A method's score between a reference (0) and a better bound (1) over ``n`` paired units.

    Attributes:
        n: number of units (each with the method's, the reference's and the bound's error).
        score: mean over units of ``(reference_i − method_i) / gap``, ``gap`` = mean(reference − bound):
            (mean reference − mean method) / (mean reference − mean bound).
        low, high: bootstrap interval of ``score`` at ``level``, the triples resampled together (the gap too);
            NaN when n < 2.
        per_unit: the per-unit scores ``(reference_i − method_i) / gap``.
        worst: the lowest per-unit score.
        gap: the mean reference-to-bound gap (errors' unit).
    """

    n: int
    score: float
    low: float
    high: float
    per_unit: tuple[float, ...]
    worst: float
    gap: float
    level: float = DEFAULT_LEVEL

    def text(self, digits: int = 2) -> str:
        """ "score [low, high]" with ``digits`` decimals."""
        return f"{self.score:.{digits}f} [{self.low:.{digits}f}, {self.high:.{digits}f}]"


def normalised_score(
    method, reference, bound, n_boot: int = DEFAULT_BOOT, seed: int = 0, level: float = DEFAULT_LEVEL
) -> Normalised:
    """``method``'s errors normalised between ``reference``'s (0) and ``bound``'s (1), unit by unit (equal-length
    arrays, entry i of each from unit i): see :class:`Normalised`. The interval resamples units with
    :func:`resamples`. ValueError naming the bad input, or when the bound is not better than the reference on
    average (no gap to normalise by)."""
    m, r, b = (_scores(name, v) for name, v in (("method", method), ("reference", reference), ("bound", bound)))
    if not len(m) == len(r) == len(b):
        raise ValueError(f"method, reference and bound must pair unit by unit: {len(m)}, {len(r)}, {len(b)} errors")
    _check_boot(n_boot, level)
    gap = float(np.mean(r - b))
    if not gap > 0:
        raise ValueError(f"the bound is not better than the reference on average (gap {gap:.4g}): no normalised score")
    per_unit = (r - m) / gap
    n = len(m)
    nan = float("nan")
    low = high = nan
    if n >= 2:
        boot = np.concatenate(
            [np.mean(r[i] - m[i], axis=1) / np.mean(r[i] - b[i], axis=1) for i in resamples(n, n_boot, seed)]
        )
        low, high = (float(x) for x in np.quantile(boot, [(1 - level) / 2, (1 + level) / 2]))
    return Normalised(
        n, float(per_unit.mean()), low, high, tuple(map(float, per_unit)), float(per_unit.min()), gap, level
    )
