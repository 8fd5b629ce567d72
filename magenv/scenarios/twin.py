"""Twin scenarios: ``twin:PATH`` — a simulated trial made from a real recording's own true motion.

``make_trial("twin:/path/to/02_undisturbed_slow_rotation_B.hdf5", seed, **overrides)`` (through
``magenv.scenarios``) loads the recording (``magenv.recordings.load_recording``), fits its sensor errors and
disturbance once (``magenv.scenarios.twin_fit``; cached, see :func:`cache_dir`) and synthesises its sensor
channels from the truth. The twin keeps the recording's truth (``q_true`` with its NaN rows, the same
``score_mask``, ``field_norm``, ``field_dip`` and ``truth``), so every method runs on both and is scored
the same way; only the sensor channels differ. Overrides are :class:`TwinConfig` fields.

Sensor channels, sensor frame, at sample i (``Motion``: qs the bridged, smoothed truth, ω its body rate):

* gyroscope, rad/s: g_i = (I + K)·ω(t_i − L_g) + b(t_i) + σ_g·n_i — K, L_g, b(t) and σ_g fitted.
* accelerometer, m/s²: a_i = R(qs(t_i − L_a))ᵀ(p̈ + g e_up) + α × r + ω × (ω × r) + b_a + σ_a·n_i
  (lever arm r, b_a, L_a, σ_a fitted; ``acc="static"``: gravity only, R(qs)ᵀ g e_up + σ_a·n_i).
* magnetometer, µT: at each new (not held) sample a conversion
  c_i = M·R(qs(t_i − L_m))ᵀ·(h_E + B_dip(p(t_i − L_m))) + o + s(t_i)·d + σ_m·ν_i,
  held samples repeat the last conversion (``magenv.sim.sensors.hold_samples``). B_dip: the fitted
  magnet at rest (``disturbance`` "dipole"); s·d: the fitted attached magnet (``disturbance`` "attached");
  ν: ``magenv.sim.sensors.noise_121`` over the conversions (the unit's low-pass noise colour) or white.

Drawn per seed (three independent streams spawned from ``numpy.random.SeedSequence(seed)``: gyroscope,
accelerometer, magnetometer): every noise sequence and, with ``hold="sim"``, the hold pattern's phase.
Everything else comes from the fit, so the same seed gives the same trial bit for bit.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import os
from pathlib import Path
from typing import Any

import numpy as np

from magenv import quaternion as quat
from magenv.recordings import load_recording
from magenv.scenarios import twin_fit
from magenv.scenarios.world import config_json
from magenv.sim import truth_motion as tm
from magenv.sim.sensors import hold_pattern, hold_samples, noise_121
from magenv.trial import META_SCENARIO, META_SEED, Trial

PREFIX = "twin:"
CACHE_DIR_ENV = "MAGENV_CACHE_DIR"


@dataclasses.dataclass(frozen=True)
class TwinConfig:
    """How a twin's sensors are made (module docstring). Defaults: everything as fitted.

    Attributes:
        gyr_lag: gyroscope delay behind the truth, samples (None: fitted, BROAD ~1.2).
        gyr_scale: apply the fitted scale / misalignment K (False: I).
        gyr_bias: ``"fitted"`` (the bias trajectory b(t)), ``"constant"`` (its rest value) or ``"none"``.
        acc: ``"model"`` (the motion's specific force at the fitted lever arm) or ``"static"`` (gravity only).
        mag_lag: magnetometer conversion delay behind the truth, samples (None: fitted, BROAD ~4.2).
        hold: ``"real"`` (the recording's own hold mask), ``"sim"`` (the simulator's ⌊i·(1 − f) + φ⌋ pattern,
            φ drawn per seed) or ``"none"``.
        hold_fraction: f of ``hold="sim"``, in [0, 1).
        mag_colour: ``"121"`` (low-pass noise over the conversions) or ``"white"``.
        disturbance: ``"fitted"`` (the recording's magnet, if its fit found one) or ``"none"``.
        noise_scale: factor on every white-noise std (≥ 0).
    """

    gyr_lag: float | None = None
    gyr_scale: bool = True
    gyr_bias: str = "fitted"
    acc: str = "model"
    mag_lag: float | None = None
    hold: str = "real"
    hold_fraction: float = 0.29
    mag_colour: str = "121"
    disturbance: str = "fitted"
    noise_scale: float = 1.0

    def __post_init__(self) -> None:
        choices = {
            "gyr_bias": ("fitted", "constant", "none"),
            "acc": ("model", "static"),
            "hold": ("real", "sim", "none"),
            "mag_colour": ("121", "white"),
            "disturbance": ("fitted", "none"),
        }
        for key, allowed in choices.items():
            if getattr(self, key) not in allowed:
                raise ValueError(f"TwinConfig.{key} must be one of {', '.join(allowed)}, got {getattr(self, key)!r}")
        for key in ("gyr_lag", "mag_lag"):
            v = getattr(self, key)
            if v is not None and (isinstance(v, bool) or not isinstance(v, (int, float)) or not 0 <= v <= 50):
                raise ValueError(f"TwinConfig.{key} must be None or a number of samples in [0, 50], got {v!r}")
        if not isinstance(self.gyr_scale, bool):
            raise ValueError(f"TwinConfig.gyr_scale must be True or False, got {self.gyr_scale!r}")
        if not (isinstance(self.hold_fraction, (int, float)) and 0 <= self.hold_fraction < 1):
            raise ValueError(f"TwinConfig.hold_fraction must be in [0, 1), got {self.hold_fraction!r}")
        if not (isinstance(self.noise_scale, (int, float)) and np.isfinite(self.noise_scale) and self.noise_scale >= 0):
            raise ValueError(f"TwinConfig.noise_scale must be a finite number ≥ 0, got {self.noise_scale!r}")


def is_twin(name) -> bool:
    """Whether ``name`` is a twin scenario (a string ``"twin:PATH"``)."""
    return isinstance(name, str) and name.startswith(PREFIX)


def recording_path(name: str) -> Path:
    """The recording file of twin scenario ``name``; ValueError if it is not ``twin:PATH`` of a file."""
    if not is_twin(name) or not name[len(PREFIX) :]:
        raise ValueError(f"a twin scenario is 'twin:PATH' with PATH a recording file, got {name!r}")
    path = Path(name[len(PREFIX) :]).expanduser()
    if not path.is_file():
        raise ValueError(f"twin scenario {name!r}: no recording file {str(path)!r}")
    return path.resolve()


def configure(name: str, **overrides) -> TwinConfig:
    """The :class:`TwinConfig` of twin scenario ``name`` with ``overrides``; ValueError naming an unknown key."""
    recording_path(name)
    known = {f.name for f in dataclasses.fields(TwinConfig)}
    unknown = sorted(k for k in overrides if k not in known)
    if unknown:
        raise ValueError(
            f"unknown parameter(s) {', '.join(map(repr, unknown))} for twin scenario {name!r}; "
            f"known: {', '.join(sorted(known))}"
        )
    try:
        return dataclasses.replace(TwinConfig(), **overrides)
    except (ValueError, TypeError) as exc:
        raise ValueError(f"twin scenario {name!r}: bad parameter value: {exc}") from None


# ---------------------------------------------------------------- the fit cache


def cache_dir() -> Path:
    """Where fitted twins are cached: ``$MAGENV_CACHE_DIR/twin``, else ``$XDG_CACHE_HOME/magenv/twin``
    (default ``~/.cache/magenv/twin``). Never next to the data."""
    if os.environ.get(CACHE_DIR_ENV):
        return Path(os.environ[CACHE_DIR_ENV]) / "twin"
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "magenv" / "twin"


def cache_file(path: Path) -> Path:
    """The cache file of recording ``path``: its stem, the SHA-256 of its bytes and the fit version."""
    digest = hashlib.sha256(Path(path).read_bytes()).hexdigest()[:16]
    return cache_dir() / f"{Path(path).stem}-{digest}-v{twin_fit.FIT_VERSION}.npz"


def save_fit(fit: twin_fit.TwinFit, file: Path) -> Path:
    """Write ``fit`` as an ``.npz`` of plain arrays (atomically: a temporary file, then renamed)."""
    file.parent.mkdir(parents=True, exist_ok=True)
    tmp = file.with_name(f"{file.stem}.{os.getpid()}.tmp.npz")
    arrays: dict[str, Any] = fit.to_arrays()
    np.savez(tmp, **arrays)
    os.replace(tmp, file)
    return file


def load_fit(file: Path) -> twin_fit.TwinFit:
    """Read a fit written by :func:`save_fit` (``allow_pickle=False``: nothing in the file can run code)."""
    with np.load(file, allow_pickle=False) as data:
        return twin_fit.TwinFit.from_arrays({k: data[k] for k in data.files})


@functools.lru_cache(maxsize=16)
def _fitted(path_text: str) -> tuple[Trial, twin_fit.Motion, twin_fit.TwinFit]:
    """(recording, motion, fit) of a recording file, fitted or read from the cache (once per process)."""
    path = Path(path_text)
    rec = load_recording(path)
    mo = twin_fit.motion_of(rec)
    file = cache_file(path)
    fit = None
    if file.is_file():
        try:
            fit = load_fit(file)
        except (ValueError, OSError, KeyError):
            fit = None  # unreadable or of another layout: fit again
        if fit is not None and (fit.version != twin_fit.FIT_VERSION or fit.n != rec.n):
            fit = None
    if fit is None:
        fit = twin_fit.fit_recording(rec, mo)
        save_fit(fit, file)
    return rec, mo, fit


def fitted(name: str) -> tuple[Trial, twin_fit.Motion, twin_fit.TwinFit]:
    """(recording, motion, fit) of twin scenario ``name`` (the fit is made once and cached)."""
    return _fitted(str(recording_path(name)))


# ---------------------------------------------------------------- the twin


def _gyro(mo, fit, cfg, rng) -> np.ndarray:
    w = tm.delay(mo.w, fit.gyr_lag if cfg.gyr_lag is None else cfg.gyr_lag)
    if cfg.gyr_scale:
        w = w @ (np.eye(3) + fit.gyr_K).T
    bias = {"fitted": fit.gyr_bias, "constant": mo.gyr_bias0, "none": np.zeros(3)}[cfg.gyr_bias]
    return w + bias + cfg.noise_scale * fit.gyr_noise * rng.standard_normal(w.shape)


def _accel(mo, fit, cfg, rng) -> np.ndarray:
    if cfg.acc == "static":
        a = quat.rotate_inv(mo.qs, np.broadcast_to(quat.gravity_up(), mo.qs[:, 1:].shape))
    else:
        a = twin_fit.acc_model(mo, fit.acc_lever, fit.acc_bias, fit.acc_lag)
    return a + cfg.noise_scale * fit.acc_noise * rng.standard_normal(a.shape)


def _magnetometer(mo, fit, cfg, rng) -> np.ndarray:
    n = fit.n
    lag = fit.mag_lag if cfg.mag_lag is None else cfg.mag_lag
    field = np.broadcast_to(fit.mag_h_E, (n, 3))
    magnet = cfg.disturbance == "fitted"
    if magnet and fit.disturbance == "dipole":
        field = field + twin_fit.dipole_e(tm.delay(mo.pos, lag), fit.dipole_pos, fit.dipole_moment)
    clean = quat.rotate_inv(tm.delay_quat(mo.qs, lag), np.ascontiguousarray(field)) @ fit.mag_M.T + fit.mag_o
    if magnet and fit.disturbance == "attached":
        clean = clean + fit.attached_profile[:, None] * fit.attached_offset
    phase = rng.uniform()  # drawn whatever the hold, so the noise below does not depend on it
    held = {"real": fit.mag_held, "none": np.zeros(n, bool)}.get(cfg.hold)
    if held is None:
        held = hold_pattern(n, cfg.hold_fraction, phase)
    new = np.flatnonzero(~held)
    z = rng.standard_normal((len(new), 3))
    noise = noise_121(z) if cfg.mag_colour == "121" else z
    values = np.empty((n, 3))
    values[new] = clean[new] + cfg.noise_scale * fit.mag_noise * noise
    return hold_samples(values, held)


def make_twin(
    rec: Trial, mo: twin_fit.Motion, fit: twin_fit.TwinFit, cfg: TwinConfig, seed: int, scenario: str
) -> Trial:
    """The twin trial of recording ``rec`` (its ``mo`` and ``fit``) for ``seed`` (module docstring)."""
    if fit.n != rec.n:
        raise ValueError(f"twin fit has {fit.n} samples, recording {rec.name!r} has {rec.n}")
    rg, ra, rm = (np.random.default_rng(s) for s in np.random.SeedSequence(int(seed)).spawn(3))
    meta = {
        META_SCENARIO: f"{PREFIX}{rec.name}",
        META_SEED: int(seed),
        "recording": scenario[len(PREFIX) :],
        "disturbance_model": fit.disturbance,
        "fitted": {"gyr_lag": fit.gyr_lag, "mag_lag": fit.mag_lag, "acc_lag": fit.acc_lag},
        "config": config_json(cfg),
    }
    return Trial(
        name=f"{PREFIX}{rec.name}#{seed}",
        rate=rec.rate,
        gyr=_gyro(mo, fit, cfg, rg),
        acc=_accel(mo, fit, cfg, ra),
        mag=_magnetometer(mo, fit, cfg, rm),
        q_true=rec.q_true.copy(),
        field_norm=rec.field_norm,
        field_dip=rec.field_dip,
        score_mask=np.array(rec.score_mask, bool, copy=True),
        truth={k: np.array(v, copy=True) for k, v in rec.truth.items()},
        meta=meta,
    )


def make_trial(name: str, seed: int, **overrides) -> Trial:
    """Twin trial ``seed`` (int ≥ 0) of twin scenario ``name`` = ``"twin:PATH"`` with :class:`TwinConfig`
    ``overrides``: the same Trial bit for bit every time."""
    cfg = configure(name, **overrides)
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"seed must be an integer ≥ 0, got {seed!r}")
    rec, mo, fit = fitted(name)
    return make_twin(rec, mo, fit, cfg, int(seed), name)


__all__ = ["PREFIX", "TwinConfig", "cache_dir", "configure", "fitted", "is_twin", "make_trial", "make_twin"]
