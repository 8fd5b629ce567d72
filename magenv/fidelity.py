"""Simulator fidelity: each method's error on a real recording beside its error on the recording's twins.

A twin (``twin:PATH``, ``magenv.scenarios.twin``) shares the recording's truth and motion; only its sensor
channels are simulated. So if the simulator's sensor and disturbance model is right, every method should
score about the same on both, and rank the same way. :func:`measure` runs each method on a recording and
on its twins (one per seed), :func:`summarize` gives

* Spearman's ρ between the methods' real and twin RMSEs (total error, degrees): per recording, per
  recording group (RMSEs averaged over the group's recordings first) and overall (averaged over all);
* per method, the ratio real / twin of those all-recording means (1: the twin predicts the real error).

Scores are ``magenv.metrics.score`` over the recording's score mask (the dataset's protocol: NaN truth
rows skipped), the same for real and twin. Twin seeds are < 5000 (reported figures).
"""

from __future__ import annotations

import csv
import dataclasses
import math
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from magenv import evaluation, scenarios
from magenv.recordings import load_recording

CSV_COLUMNS = ("recording", "method", "real_total", "twin_total", "real_heading", "twin_heading")
#: Recording groups by a word of the BROAD file name, in this order (first match); else "other".
GROUP_WORDS = ("undisturbed", "tapping", "vibration", "stationary_magnet", "attached_magnet", "office", "mixed")
#: The methods `magenv fidelity` runs by default: the references, the blend and Kalman-trust rules at
#: published and tuned values, the TRIAD/QUEST and QSF families.
DEFAULT_METHODS = (
    "vqf,fusion,mimu,imu,fan_lambda,fan_lambda_tuned,threshold,threshold_tuned,kf_nominal,kf_gate,"
    "kf_gate_tuned,kf_adaptive,kf_adaptive_tuned,kf_model,kf_model_tuned,th_triad,th_quest,mod_triad,"
    "mod_quest,aekf,magyq,delay_magyq,delay_magyq_tuned,qsf_detector_tuned"
)
#: The trust rules (policies acting on features): the λ rules, the Kalman-trust rules and the QSF detector,
#: at published and tuned values; the target band of their real / twin ratio is ``RATIO_BAND``.
RULES = (
    "fan_lambda,fan_lambda_tuned,threshold,threshold_tuned,kf_nominal,kf_gate,kf_gate_tuned,kf_adaptive,"
    "kf_adaptive_tuned,kf_model,kf_model_tuned,qsf_detector_tuned"
).split(",")
#: The target band of the real / twin ratio (issue 17).
RATIO_BAND = (0.67, 1.5)


@dataclasses.dataclass(frozen=True)
class Row:
    """One method on one recording: real RMSE and the twin RMSEs (one per seed), degrees."""

    recording: str
    method: str
    real_total: float
    real_heading: float
    twin_totals: tuple[float, ...]
    twin_headings: tuple[float, ...]
    error: str = ""  # why a run failed (its scores are NaN)

    @property
    def twin_total(self) -> float:
        return _mean(self.twin_totals)

    @property
    def twin_heading(self) -> float:
        return _mean(self.twin_headings)

    def as_csv(self) -> dict[str, Any]:
        return {
            "recording": self.recording,
            "method": self.method,
            "real_total": self.real_total,
            "twin_total": self.twin_total,
            "real_heading": self.real_heading,
            "twin_heading": self.twin_heading,
        }


def _mean(x) -> float:
    x = np.asarray(x, float)
    return float(np.mean(x)) if x.size and np.all(np.isfinite(x)) else math.nan


def group_of(recording: str) -> str:
    """The recording group of a recording name (the first of ``GROUP_WORDS`` in it, else ``"other"``)."""
    return next((w for w in GROUP_WORDS if w in recording), "other")


def _score(name: str, make_method: Callable[[str], Any], trial) -> tuple[float, float, str]:
    try:
        s = evaluation.run_method(name, make_method(name), trial).scored
        return float(s.total), float(s.heading), ""
    except Exception as exc:  # one method failing on one trial is a result, not the end of the measurement
        return math.nan, math.nan, f"{type(exc).__name__}: {exc}"


def measure(
    recordings: Sequence[str | Path],
    methods: Sequence[str],
    make_method: Callable[[str], Any],
    seeds: Sequence[int],
    twin_overrides: dict | None = None,
    progress: Callable[[str], None] | None = None,
) -> list[Row]:
    """Rows of every method on every recording and its twins (``twin:PATH`` with ``seeds`` and
    ``twin_overrides``, TwinConfig fields). ``make_method(name)`` makes a fresh method object per run."""
    if not seeds:
        raise ValueError("fidelity needs at least one twin seed")
    rows = []
    for path in recordings:
        rec = load_recording(path)
        twins = [scenarios.make_trial(f"twin:{path}", int(s), **(twin_overrides or {})) for s in seeds]
        for m in methods:
            real_t, real_h, err = _score(m, make_method, rec)
            tw = [_score(m, make_method, t) for t in twins]
            errors = "; ".join(e for e in [err, *(t[2] for t in tw)] if e)
            rows.append(Row(rec.name, m, real_t, real_h, tuple(t[0] for t in tw), tuple(t[1] for t in tw), errors))
        if progress is not None:
            progress(f"{rec.name}: {len(methods)} methods on the recording and {len(twins)} twins")
    return rows


def spearman(a, b) -> float:
    """Spearman's rank correlation of the finite pairs of ``a`` and ``b`` (NaN below 3 pairs or if constant)."""
    from scipy.stats import spearmanr

    a, b = np.asarray(a, float), np.asarray(b, float)
    ok = np.isfinite(a) & np.isfinite(b)
    if ok.sum() < 3 or np.ptp(a[ok]) == 0 or np.ptp(b[ok]) == 0:
        return math.nan
    return float(spearmanr(a[ok], b[ok]).statistic)


def _matrix(rows: Sequence[Row]):
    recs = list(dict.fromkeys(r.recording for r in rows))
    methods = list(dict.fromkeys(r.method for r in rows))
    R = np.full((len(methods), len(recs)), np.nan)
    T = np.full_like(R, np.nan)
    for r in rows:
        i, j = methods.index(r.method), recs.index(r.recording)
        R[i, j], T[i, j] = r.real_total, r.twin_total
    return recs, methods, R, T


@dataclasses.dataclass(frozen=True)
class Summary:
    """Spearman ρ per recording, per group and overall; per method the real and twin means and their ratio."""

    rho_recording: dict[str, float]
    rho_group: dict[str, float]
    rho_overall: float
    real_mean: dict[str, float]
    twin_mean: dict[str, float]

    def ratio(self, method: str) -> float:
        return self.real_mean[method] / self.twin_mean[method]

    def in_band(self, methods: Sequence[str] | None = None) -> tuple[int, int]:
        """(how many of ``methods`` (default all) have real / twin within ``RATIO_BAND``, how many)."""
        ms = list(self.real_mean) if methods is None else [m for m in methods if m in self.real_mean]
        lo, hi = RATIO_BAND
        return sum(lo <= self.ratio(m) <= hi for m in ms), len(ms)


def summarize(rows: Sequence[Row]) -> Summary:
    """The :class:`Summary` of ``rows`` (module docstring)."""
    recs, methods, R, T = _matrix(rows)
    groups: dict[str, list[int]] = {}
    for j, r in enumerate(recs):
        groups.setdefault(group_of(r), []).append(j)
    with np.errstate(all="ignore"):
        rm, tm = np.nanmean(R, 1), np.nanmean(T, 1)
        return Summary(
            rho_recording={r: spearman(R[:, j], T[:, j]) for j, r in enumerate(recs)},
            rho_group={g: spearman(np.nanmean(R[:, js], 1), np.nanmean(T[:, js], 1)) for g, js in groups.items()},
            rho_overall=spearman(rm, tm),
            real_mean=dict(zip(methods, rm.tolist())),
            twin_mean=dict(zip(methods, tm.tolist())),
        )


def write_csv(rows: Sequence[Row], path: str | Path) -> Path:
    """Write ``rows`` with the header ``CSV_COLUMNS`` (RMSEs in degrees, the twin ones means over seeds)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=CSV_COLUMNS)
        w.writeheader()
        for r in rows:
            w.writerow({k: (f"{v:.4f}" if isinstance(v, float) else v) for k, v in r.as_csv().items()})
    return path


def plot(rows: Sequence[Row], path: str | Path, title: str = "real vs twin RMSE per method") -> Path:
    """Log-log scatter of real against twin total RMSE, one point per method and recording, coloured by
    recording group; the line real = twin and the band ``RATIO_BAND`` around it."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    path = Path(path)
    fig, ax = plt.subplots(figsize=(6.5, 6))
    by_group: dict[str, list[Row]] = {}
    for r in rows:
        by_group.setdefault(group_of(r.recording), []).append(r)
    vals = [v for r in rows for v in (r.real_total, r.twin_total) if math.isfinite(v) and v > 0]
    lo, hi = (min(vals) / 1.5, max(vals) * 1.5) if vals else (0.1, 100.0)
    for g, rs in by_group.items():
        ax.scatter([r.twin_total for r in rs], [r.real_total for r in rs], s=14, alpha=0.8, label=g, zorder=3)
    xs = np.geomspace(lo, hi, 50)
    ax.plot(xs, xs, "k-", lw=0.8, zorder=2)
    ax.fill_between(xs, xs * RATIO_BAND[0], xs * RATIO_BAND[1], color="0.88", lw=0, zorder=1)
    ax.set(xscale="log", yscale="log", xlim=(lo, hi), ylim=(lo, hi), xlabel="twin RMSE (°)", ylabel="real RMSE (°)")
    s = summarize(rows)
    ax.set_title(f"{title}\nSpearman ρ overall {s.rho_overall:+.2f}", fontsize=10)
    ax.legend(fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def markdown(rows: Sequence[Row], rules: Sequence[str] = ()) -> str:
    """A Markdown report: per method the real and twin means over the recordings and their ratio; ρ per
    recording, group and overall; how many of ``rules`` are within ``RATIO_BAND``."""
    s = summarize(rows)
    lines = ["| method | real mean (°) | twin mean (°) | real / twin |", "|---|---|---|---|"]
    for m in s.real_mean:
        lines.append(f"| `{m}` | {s.real_mean[m]:.2f} | {s.twin_mean[m]:.2f} | {s.ratio(m):.2f} |")
    lines += ["", "| Spearman ρ | " + " | ".join(s.rho_recording) + " |", "|---" * (len(s.rho_recording) + 1) + "|"]
    lines.append("| per recording | " + " | ".join(f"{v:+.2f}" for v in s.rho_recording.values()) + " |")
    lines += ["", "| Spearman ρ | " + " | ".join(s.rho_group) + " | overall |", "|---" * (len(s.rho_group) + 2) + "|"]
    lines.append("| groups | " + " | ".join(f"{v:+.2f}" for v in s.rho_group.values()) + f" | {s.rho_overall:+.2f} |")
    if rules:
        k, n = s.in_band(rules)
        lines += ["", f"rules with real / twin in [{RATIO_BAND[0]}, {RATIO_BAND[1]}]: {k} of {n}"]
    return "\n".join(lines)
