"""Probe: can any MagQSF-v0 decision steer a known heading error back toward zero?

    python -m studies.probe_qsf_steering [--scenario handheld_texting] [--trials 6] [--every 20]
        [--hold 10] [--horizon 5] [--json FILE]
    python -m studies.probe_qsf_steering --levers [--scenario …] [--trials 6] [--validation]

It rolls the tuned QSF detector (``qsf_detector_tuned``'s thresholds; the
continuation rule of ``oracle_qsf``, ``baselines/oracle_qsf.py``) through the
env's runner on ``--trials`` training trials (seeds 10000, …) and, every
``--every`` decisions where the rule keeps an active period and ``--horizon``
seconds remain, forks the filter state (``magenv.filters.qsf.State``): one
branch goes on with the rule, one per departure takes the departure for
``--hold`` decisions and then the rule. Departures: the env's none, keep with
trust 0.3 and start (trust 1), and — outside the env's action box, through
the filter kernel directly — keep with trust 2 (the magnetic update's gain
doubled). Per fork it records

* e: the estimate's true signed heading error at the fork (yaw of
  q̂ ⊗ q_true*, °, ``magenv.metrics.euler_error``);
* m: a causal estimate of e: the heading of q̂ y_m q̂* (ENU, ``atan2(east,
  north)``) averaged (circular mean) over the fork's last 2 s, minus its
  circular mean over the trial's first 0.5 s (the hand-held filters start
  from truth, §5.3: where the field keeps its direction, m follows e);
* Δe: the departure's signed heading error minus the rule's, averaged over
  the last 2 s of the horizon;
* Δcost: the departure's mean squared total error over the horizon minus the
  rule's (°²; < 0: the departure pays).

It prints per departure the least-squares slope of Δe on e (< 0: the
departure moves the error toward zero, so a policy that knows its error
could steer with it; > 0: away), the correlations of Δe with e and with m,
the share of forks where the departure pays and where it moves the error
toward zero, and the correlation of m with e.

``--levers`` asks instead whether a policy could use a magnetic gain above
the box: it runs the same rule over whole trials with every magnetic update's
gain multiplied by a constant (``LEVERS``: 1.25 … 2) or by 1.5 or 2 only where
|m| exceeds a threshold, and with the filter's magnetometer noise σ_m (µT; the
paper's 0.1 m0 by default) set to a constant or lowered only where |m|
exceeds a threshold (the filter's parameters swapped between decisions), and
prints each variant's paired ratio to the rule as it is (geometric mean of the
per-trial RMSE ratios); ``--validation`` runs it on validation seeds (5000, …)
instead, to check a variant chosen on the training trials. This is a measurement (it prints figures), not a test.
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

import magenv  # noqa: F401
from magenv import metrics, registry
from magenv.baselines.oracle_qsf import QSFOracle, rule_code
from magenv.envs.qsf import decode_action, fill_decision
from magenv.filters import qsf
from magenv.quaternion import rotate1
from magenv.scenarios import make_trial
from magenv.seeding import HELD_OUT_BELOW, VALIDATION_START

#: departure name → (magnetic action code, trust); "keep, trust 2" lies outside the env's action box
DEPARTURES = {
    "none": (qsf.MAG_NONE, 0.0),
    "keep, trust 0.3": (qsf.MAG_KEEP, 0.3),
    "start": (qsf.MAG_START, 1.0),
    "keep, trust 2 (outside the box)": (qsf.MAG_KEEP, 2.0),
}
START_S, TAIL_S, CAUSAL_S = 0.5, 2.0, 2.0  # H0 window, Δe averaging window, m's averaging window


def _circular_mean_deg(h: np.ndarray) -> float:
    return float(np.degrees(np.angle(np.mean(np.exp(1j * np.radians(h))))))


def _wrap(deg):
    """Angles (°, a float or an array) wrapped to [−180, 180)."""
    return (deg + 180.0) % 360.0 - 180.0


def _mag_heading(q: np.ndarray, mag: np.ndarray) -> np.ndarray:
    """(n,) heading (°) of q̂_i y_m,i q̂_i* for rows i."""
    v = np.array([rotate1(qi, mi) for qi, mi in zip(q, mag)])
    return np.degrees(np.arctan2(v[:, 0], v[:, 1]))


class ErrorEstimate:
    """The causal estimate m of the heading error (module docstring) along one trial's estimate ``q`` (N, 4):
    ``at(j)`` reads rows < j only; None until the start window has passed."""

    def __init__(self, trial, q: np.ndarray):
        self.trial, self.q, self.h0 = trial, q, None
        self.start, self.window = (int(round(s * trial.rate)) for s in (START_S, CAUSAL_S))

    def at(self, j: int) -> float | None:
        if self.h0 is None and j >= self.start:
            self.h0 = _circular_mean_deg(_mag_heading(self.q[:j], self.trial.mag[:j]))
        if self.h0 is None or j < self.window:
            return None
        a = j - self.window
        return _wrap(_circular_mean_deg(_mag_heading(self.q[a:j], self.trial.mag[a:j])) - self.h0)


def _switch(high, low, threshold: float):
    """m → ``high`` where |m| exceeds ``threshold`` (°), else ``low`` (also before m exists)."""
    return lambda m: high if m is not None and abs(m) > threshold else low


def _const(value):
    """m → ``value``."""
    return lambda m: value


#: --levers: name → (trust of m, σ_m of m in µT or None for the filter's default); trust above 1 lies outside the box
LEVERS = {
    **{f"trust {c:g}": (_const(c), _const(None)) for c in (1.25, 1.5, 1.75, 2.0)},
    **{f"trust {c:g} where m is beyond ±{t:g}°": (_switch(c, 1.0, t), _const(None)) for c in (1.5, 2.0)
       for t in (0.5, 1.0, 2.0)},
    **{f"σ_m {s:g} µT": (_const(1.0), _const(s)) for s in (2.0, 1.0, 0.5)},
    **{f"σ_m {s:g} µT where m is beyond ±{t:g}°": (_const(1.0), _switch(s, None, t)) for s in (1.0, 2.0)
       for t in (0.5, 1.0, 2.0)},
}  # fmt: skip


def _roll(oracle: QSFOracle, runner, first, hold: int, stop: int) -> np.ndarray:
    """The estimate (stop − pos, 4) from ``runner``'s state (left unchanged): ``first`` (code, trust) for ``hold``
    decisions (a start only at its first sample, then keep), then the rule; NaN rows after a filter failure."""
    k, n = oracle.decision_every, runner.n
    work = qsf.State(*(a.copy() for a in runner.state))
    sensors = runner.inputs
    inputs = qsf.Inputs(sensors.gyr, sensors.acc, sensors.mag, np.zeros(n, np.int8), np.zeros(n))
    out = qsf.Outputs.empty(n)
    j, d = runner.pos, 0
    while j < stop:
        b = min(j + k, stop)
        if first is not None and d < hold:
            code = first[0] if d == 0 else (qsf.MAG_KEEP if first[0] == qsf.MAG_START else first[0])
            trust = first[1]
        else:
            code, trust = rule_code(runner.codes, work.period_active[0], j), 1.0
        fill_decision(inputs, code, trust, j, b)
        bad, _ = qsf.run_kernel(runner.params, work, inputs, float(runner.trial.dt), j, b, out)
        if bad >= 0:
            out.q[bad:stop] = np.nan
            break
        j, d = b, d + 1
    return out.q[runner.pos : stop].copy()


def probe_trial(oracle: QSFOracle, trial, every: int, hold: int, horizon_s: float) -> list[list[float]]:
    """Forks of one trial: rows [e, m, Δe and Δcost per departure]."""
    runner = oracle.make_runner(trial)
    k, rate = oracle.decision_every, trial.rate
    horizon, tail = (int(round(s * rate)) for s in (horizon_s, TAIL_S))
    estimate = ErrorEstimate(trial, runner.est)
    rows, decision = [], 0
    while not runner.done:
        j = runner.pos
        action = oracle.continuation_action(runner)
        m = estimate.at(j)
        keeps = action[0] == 0.0 and runner.state.period_active[0]
        if m is not None and decision % every == every // 2 and keeps and j + horizon <= runner.n:
            e = float(metrics.euler_error(runner.est[j - 1], trial.q_true[j - 1])[0])
            truth = trial.q_true[j : j + horizon]
            base = _roll(oracle, runner, None, hold, j + horizon)
            yaw_base = metrics.euler_error(base[-tail:], truth[-tail:])[:, 0]
            cost_base = np.nanmean(metrics.errors(base, truth)[:, 0] ** 2)
            row = [e, m]
            for first in DEPARTURES.values():
                est = _roll(oracle, runner, first, hold, j + horizon)
                yaw = metrics.euler_error(est[-tail:], truth[-tail:])[:, 0]
                row += [float(np.mean(_wrap(yaw - yaw_base))),
                        float(np.nanmean(metrics.errors(est, truth)[:, 0] ** 2) - cost_base)]  # fmt: skip
            rows.append(row)
        code, trust, _ = decode_action(action)
        runner.advance(k, (code, trust))
        decision += 1
    return rows


def lever_rmse(oracle: QSFOracle, trial, trust_of, sigma_of) -> float:
    """Total RMSE (°) of the rule over ``trial`` with each decision's trust ``trust_of(m)`` and magnetometer noise
    ``sigma_of(m)`` (µT; None: the filter's own), m the causal error estimate before the decision."""
    runner = oracle.make_runner(trial)
    k, n, dt = oracle.decision_every, runner.n, float(trial.dt)
    state, sensors, out = runner.state, runner.inputs, qsf.Outputs.empty(runner.n)
    inputs = qsf.Inputs(sensors.gyr, sensors.acc, sensors.mag, np.zeros(n, np.int8), np.zeros(n))
    estimate, params = ErrorEstimate(trial, out.q), {None: runner.params}
    for j in range(0, n, k):
        m = estimate.at(j)
        sigma = sigma_of(m)
        if sigma not in params:
            params[sigma] = runner.params._replace(sigma_mag=float(sigma))
        fill_decision(inputs, rule_code(runner.codes, state.period_active[0], j), trust_of(m), j, min(j + k, n))
        if qsf.run_kernel(params[sigma], state, inputs, dt, j, min(j + k, n), out)[0] >= 0:
            return float("inf")  # the filter failed (a gain far above 1 diverges)
    return metrics.score(out.q, trial.q_true, trial.score_mask).total


def levers(oracle: QSFOracle, scenario: str, seeds: range) -> dict:
    """{variant: paired ratio to the rule} over the trials ``seeds`` of ``scenario``; prints them."""
    base, runs = [], {name: [] for name in LEVERS}
    for s in seeds:
        trial = make_trial(scenario, s)
        base.append(lever_rmse(oracle, trial, _const(1.0), _const(None)))
        for name, (trust_of, sigma_of) in LEVERS.items():
            runs[name].append(lever_rmse(oracle, trial, trust_of, sigma_of))
    ratios = {name: float(np.exp(np.mean(np.log(np.array(v) / base)))) for name, v in runs.items()}
    print(f"{scenario}, seeds {seeds.start}:{seeds.stop}: the rule {np.mean(base):.2f}° mean RMSE; ratio to it:")
    print("| variant | ratio |\n|---|---|")
    for name, ratio in ratios.items():
        print(f"| {name} | {ratio:.3f} |")
    return ratios


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenario", default="handheld_texting")
    ap.add_argument("--trials", type=int, default=6)
    ap.add_argument("--every", type=int, default=20, help="fork at every N-th decision, where the rule keeps")
    ap.add_argument("--hold", type=int, default=10, help="decisions each departure is held")
    ap.add_argument("--horizon", type=float, default=5.0, help="s after the fork")
    ap.add_argument("--levers", action="store_true", help="gains above the box and σ_m instead of the forks")
    ap.add_argument("--validation", action="store_true", help="--levers on validation seeds (5000, …)")
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    oracle = QSFOracle.from_detector_params(registry.tuned_params("delay_magyq"))
    if args.levers:
        first = VALIDATION_START if args.validation else HELD_OUT_BELOW
        out = {"scenario": args.scenario, "levers": levers(oracle, args.scenario, range(first, first + args.trials))}
        if args.json:
            with open(args.json, "w") as f:
                json.dump(out, f, indent=1)
        return
    t0, rows = time.perf_counter(), []
    for s in range(HELD_OUT_BELOW, HELD_OUT_BELOW + args.trials):
        rows += probe_trial(oracle, make_trial(args.scenario, s), args.every, args.hold, args.horizon)
    r = np.array(rows)
    e, m = r[:, 0], r[:, 1]
    took = time.perf_counter() - t0
    corr = np.corrcoef(m, e)[0, 1]
    print(f"{args.scenario}: {len(r)} forks on {args.trials} training trials ({took:.0f} s); corr(m, e) {corr:.2f}; "
          f"departures held {args.hold} decisions, horizon {args.horizon:g} s")  # fmt: skip
    print("| departure | slope Δe/e | corr(Δe, e) | corr(Δe, m) | std Δe (°) | pays | moves e toward 0 |")
    print("|---|---|---|---|---|---|---|")
    out = {"scenario": args.scenario, "forks": len(r), "corr_m_e": float(np.corrcoef(m, e)[0, 1]), "departures": {}}
    for c, name in enumerate(DEPARTURES):
        de, dc = r[:, 2 + 2 * c], r[:, 3 + 2 * c]
        ok = np.isfinite(de) & np.isfinite(dc)
        slope = float(np.polyfit(e[ok], de[ok], 1)[0])
        fig = {
            "slope": slope,
            "corr_e": float(np.corrcoef(de[ok], e[ok])[0, 1]),
            "corr_m": float(np.corrcoef(de[ok], m[ok])[0, 1]),
            "std": float(np.std(de[ok])),
            "pays": float(np.mean(dc[ok] < 0)),
            "toward_zero": float(np.mean(np.sign(de[ok]) == -np.sign(e[ok]))),
        }
        out["departures"][name] = fig
        print(f"| {name} | {slope:+.3f} | {fig['corr_e']:+.2f} | {fig['corr_m']:+.2f} | {fig['std']:.3f} | "
              f"{fig['pays']:.2f} | {fig['toward_zero']:.2f} |")  # fmt: skip
    if args.json:
        with open(args.json, "w") as f:
            json.dump(out, f, indent=1)


if __name__ == "__main__":
    main()
