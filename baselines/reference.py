"""Outside reference estimators: VQF and x-io Fusion, as ``Estimator``s.

Both are complete published filters run as their authors ship them, on any
``Trial`` (simulated at any rate, or a real recording), causally: each output
sample depends only on that and earlier samples. They are the bar a learned
magnetometer-trust policy has to clear.

* **VQF** (Laidig & Seel 2023; package ``vqf``): the online C++ class
  ``vqf.VQF(gyrTs, accTs, magTs, **params)`` stepped through the trial by its
  ``updateBatch`` (a loop of ``update`` inside C++, still causal). Default
  parameters unless given; ``magDistRejectionEnabled=False`` turns its
  magnetic disturbance rejection off. Output ``quat9D`` is sensor → ENU with
  ``[w, x, y, z]``, magenv's own convention. On BROAD it reproduces the
  dataset README's figures exactly (``tests/test_recordings.py``).
  ``trust`` is 0 where VQF reports a magnetic disturbance
  (``magDistDetected``: it then skips the magnetometer correction, or after
  ``magMaxRejectionTime`` slows it), else 1; all 1 with rejection off.
* **Fusion** (x-io Technologies, Madgwick's revised AHRS; package
  ``imufusion``): ``imufusion.Ahrs`` with the settings x-io recommends for
  most applications — gain 0.5, acceleration rejection 10°, **magnetic
  rejection 10°**, rejection timeout 5 s (imufusion 1.3 reads it in seconds
  through ``sample_rate``) — plus gyroscope range 2000 °/s (the BROAD IMU's
  range, read off its gyro resolution 0.061 °/s) and x-io's run-time gyroscope
  offset correction (``imufusion.Bias``, default settings), which x-io says
  should run with the AHRS. Earth convention **ENU** (``CONVENTION_ENU``; the
  ``AhrsSettings`` constructor of imufusion 1.3.3 ignores its ``convention``
  argument, so it is set through the property and checked). Units at the
  edge: gyro rad/s → °/s, accelerometer m/s² → g (9.81), magnetometer µT (any
  unit works). ``trust`` is 0 where Fusion ignored the magnetometer
  (``magnetometer_ignored``), else 1.

``vqf`` is a core dependency (it is also the filter of ``magenv/MagVQF-v0``);
``imufusion`` is the optional extra ``pip install magenv[reference]``. Both are
imported only when an estimator is built.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from magenv.protocols import Estimate, Estimator
from magenv.quaternion import GRAVITY
from magenv.trial import Trial

INSTALL_HINT = "pip install magenv[reference]"


def _require(module: str):
    import importlib

    try:
        return importlib.import_module(module)
    except ImportError as exc:
        raise ImportError(f"the reference estimators need the package {module!r}: {INSTALL_HINT} ({exc})") from None


class VQFEstimator:
    """Online (causal) VQF with its default parameters, or those in ``params``.

    Args:
        params: keyword parameters of ``vqf.VQF`` (e.g.
            ``magDistRejectionEnabled=False``, ``tauAcc`` s, ``tauMag`` s).
    """

    def __init__(self, **params) -> None:
        self._vqf = _require("vqf")
        self.params = dict(params)

    def run(self, trial: Trial) -> Estimate:
        """Sensor → ENU estimate of every sample of ``trial`` (rate from ``trial.rate``)."""
        ts = trial.dt
        f = self._vqf.VQF(ts, ts, ts, **self.params)
        out = f.updateBatch(
            np.ascontiguousarray(trial.gyr, float),
            np.ascontiguousarray(trial.acc, float),
            np.ascontiguousarray(trial.mag, float),
        )
        if self.params.get("magDistRejectionEnabled", True):
            trust = np.where(np.asarray(out["magDistDetected"], bool), 0.0, 1.0)
        else:  # rejection off: the magnetometer is always used (magDistDetected is then meaningless)
            trust = np.ones(trial.n)
        return Estimate(q=np.asarray(out["quat9D"], float), trust=trust)

    def __repr__(self) -> str:
        return f"VQFEstimator({', '.join(f'{k}={v!r}' for k, v in self.params.items())})"


class FusionEstimator:
    """x-io Fusion AHRS (``imufusion``) with magnetic rejection, ENU output.

    Args:
        gain: feedback gain (x-io: 0.5 suits most applications).
        acceleration_rejection: threshold, degrees (0 disables).
        magnetic_rejection: threshold, degrees (0 disables).
        rejection_timeout: recovery trigger period, s.
        gyroscope_range: °/s; rates above 98 % of it restart the filter (0 disables).
        offset_correction: run ``imufusion.Bias`` on the gyroscope first.
    """

    def __init__(
        self,
        gain: float = 0.5,
        acceleration_rejection: float = 10.0,
        magnetic_rejection: float = 10.0,
        rejection_timeout: float = 5.0,
        gyroscope_range: float = 2000.0,
        offset_correction: bool = True,
    ) -> None:
        self._fusion = _require("imufusion")
        self.gain = gain
        self.acceleration_rejection = acceleration_rejection
        self.magnetic_rejection = magnetic_rejection
        self.rejection_timeout = rejection_timeout
        self.gyroscope_range = gyroscope_range
        self.offset_correction = offset_correction

    def _settings(self, rate: float):
        fu = self._fusion
        s = fu.AhrsSettings()
        s.sample_rate = rate
        s.convention = fu.CONVENTION_ENU
        s.gain = self.gain
        s.gyroscope_range = self.gyroscope_range
        s.acceleration_rejection = self.acceleration_rejection
        s.magnetic_rejection = self.magnetic_rejection
        s.rejection_timeout = self.rejection_timeout
        if s.convention != fu.CONVENTION_ENU:
            raise RuntimeError("imufusion did not accept CONVENTION_ENU; cannot run Fusion in magenv's frame")
        return s

    def run(self, trial: Trial) -> Estimate:
        """Sensor → ENU estimate of every sample of ``trial``."""
        fu = self._fusion
        ahrs = fu.Ahrs()
        ahrs.set_settings(self._settings(trial.rate))
        ahrs.set_sample_period(trial.dt)
        bias = None
        if self.offset_correction:
            bias = fu.Bias()
            bias.set_settings(fu.BiasSettings(sample_rate=trial.rate))
        gyr = np.rad2deg(trial.gyr)  # °/s
        acc = trial.acc / GRAVITY  # g
        mag = np.ascontiguousarray(trial.mag, float)  # µT
        q = np.empty((trial.n, 4))
        trust = np.empty(trial.n)
        for i in range(trial.n):
            g = bias.update(gyr[i]) if bias is not None else gyr[i]
            ahrs.update(g, acc[i], mag[i])
            q[i] = ahrs.get_quaternion()
            trust[i] = 0.0 if ahrs.get_internal_states().magnetometer_ignored else 1.0
        return Estimate(q=q, trust=trust)

    def __repr__(self) -> str:
        return (
            f"FusionEstimator(gain={self.gain}, magnetic_rejection={self.magnetic_rejection}, "
            f"rejection_timeout={self.rejection_timeout}, offset_correction={self.offset_correction})"
        )


def methods() -> dict[str, Callable[[], Estimator]]:
    """Factories of the reference estimators by name, for ``compare``:
    ``{"vqf": VQF defaults, "fusion": Fusion as documented above}``."""
    return {"vqf": VQFEstimator, "fusion": FusionEstimator}
