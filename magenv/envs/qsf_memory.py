"""The extra causal features of ``magenv/MagQSF-v0``'s extended observation (``features="extended"``).

What the oracle (``magenv.baselines.oracle_qsf``) uses and today's observation
lacks is the *sign* of the heading error and of each magnetic correction:
MAGYQ's QSF reference only holds the heading that the estimate had at the
period's start, and whether an update (or a new period) helps depends on how
the estimate has drifted since the field was last close to the Earth field.
These features are computed from the sensors, the detector and the env's own
estimate history only — never truth — by :func:`update`, called after each
step on the samples just fused (``start:stop``); they describe the decision
at sample ``stop``, the timing of the base features.

Conventions (ENU earth frame, degrees, signed, wrapped to ±180): "heading(a ⊗
b*)" is the rotation about earth-up from orientation b to a
(``magenv.envs.blend_memory``'s convention); the *mag heading* of sample i is
the heading of its field q̂_i y_m q̂_i* (q̂_i the estimate after the sample)
minus that of the Earth field (≈ −heading error where the field is the
Earth's); the *reference heading* is the heading of q̂_i y_m q̂_i* minus that
of the QSF reference m_ref (eq. 8), 0 without a period. An EMA of time
constant τ takes each sample with weight Δt/τ. A *gyro anchor* integrates the
raw gyro (the filter's prediction without bias, eq. 17) from the estimate at
the sample it was last re-anchored. A sample is *clean* when
|‖y_m‖ − m0|/m0 < 0.05 and its dip deviation is below 3°.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numba import njit

from magenv.envs.blend_memory import _ema, _heading
from magenv.envs.features import DEG, HEADING, SHARED, Feature, FeatureTable
from magenv.envs.headings import dip_deg, norm3, planar_heading, wrap_deg
from magenv.filters.qsf import SIGNAL
from magenv.quaternion import GRAVITY, from_rotvec1, mul1, normalize1, rotate1

EXTRA = FeatureTable(
    SHARED["mh_ema_1"],
    SHARED["mh_ema_4"],
    Feature("mh_ema_16", *HEADING, DEG, "EMA (τ 16 s) of the mag heading"),
    Feature("mh_clean", *HEADING, DEG, "EMA (τ 2 s) of the mag heading over clean samples only"),
    SHARED["clean_ema_4"],
    SHARED["t_clean"],
    Feature("d_anchor", *HEADING, DEG, "heading(q̂ ⊗ q_anc*), q_anc the gyro anchor re-anchored on clean samples"),
    Feature(
        "d_period",
        *HEADING,
        DEG,
        "heading(q̂ ⊗ q_per*), q_per the gyro anchor re-anchored at each period start and outside periods "
        "(what the QSF updates turned since the period began)",
    ),
    Feature("ref_h", *HEADING, DEG, "reference heading of the last fused sample (0 without period)"),
    Feature("ref_h_ema_05", *HEADING, DEG, "EMA (τ 0.5 s, one update per step) of `ref_h`"),
    Feature("spread_ema_1", 0.0, 100.0, "th_spread", "EMA (τ 1 s) of the detector's spread"),
    Feature("innov_ema_1", 0.0, 100.0, "σ_m", "EMA (τ 1 s) of ‖δz‖ (eq. 9) over the samples of a period"),
    Feature("nd_ema_2", -1.0, 20.0, "fraction of m0", "EMA (τ 2 s) of (‖y_m‖ − m0)/m0"),
    Feature("dd_ema_2", *HEADING, DEG, "EMA (τ 2 s) of the signed dip deviation of q̂ y_m q̂*"),
    SHARED["gyro_ema_1"],
    Feature("acc_ema_05", 0.0, 10.0, "fraction of g", "EMA (τ 0.5 s) of |‖y_a‖ − g|/g"),
)
X = EXTRA.ix
_LOW, _HIGH = EXTRA.low64, EXTRA.high64
LAGS = (10, 40)  # decisions: 1 s and 4 s at the env's default k = 10, 100 Hz

# layout of the state vector: two quaternions, then the scalars
Q_ANC, Q_PER = 0, 4
(S_MH1, S_MH4, S_MH16, S_MHC, S_CLEAN4, S_TCLEAN, S_REFH, S_REF05, S_SPR1, S_INN1, S_ND2, S_DD2, S_G1,
 S_ACC05) = range(8, 22)  # fmt: skip
N_STATE = 22
CLEAN_NORM, CLEAN_DIP_DEG = 0.05, 3.0


class Memory(NamedTuple):
    """The streaming state of the extra features of one trial (arrays updated in place)."""

    state: np.ndarray  # (N_STATE,) see the layout constants
    value: np.ndarray  # (len(EXTRA),) the features of the next decision (zeros before any sample is fused)

    @classmethod
    def start(cls, q0: np.ndarray) -> Memory:
        """Memory at the start of a trial: both anchors at the start ``q0``."""
        state = np.zeros(N_STATE)
        state[Q_ANC : Q_ANC + 4] = q0
        state[Q_PER : Q_PER + 4] = q0
        return cls(state, np.zeros(len(EXTRA)))


@njit(cache=True)
def update(p, state, inputs, out, spread, site, dt, mem, start, stop):
    """Advance ``mem`` (:class:`Memory`) over the fused samples start:stop and write ``mem.value``.

    ``p``, ``state``: the env's ``qsf.Params`` and ``qsf.State`` after the step; ``inputs``, ``out``: its
    ``qsf.Inputs`` and ``qsf.Outputs`` (rows
    start:stop written); ``spread`` (N,) the detector's spread in units of th_spread; ``site`` (m0 µT,
    θ0 °); ``dt`` s."""
    s, val = mem.state, mem.value
    if stop <= start:
        return
    m0, dip0 = site
    e = p.earth_field
    h_e = np.rad2deg(np.arctan2(e[0], e[1]))
    sigma_m = p.sigma_mag
    for i in range(start, stop):
        q = out.q[i]
        mag = inputs.mag[i]
        me = rotate1(q, mag)
        mn = norm3(mag)
        mh = wrap_deg(planar_heading(me) - h_e)
        s[S_MH1] = _ema(s[S_MH1], mh, dt)
        s[S_MH4] = _ema(s[S_MH4], mh, dt / 4.0)
        s[S_MH16] = _ema(s[S_MH16], mh, dt / 16.0)
        nd = (mn - m0) / m0
        dip = dip_deg(me, mn, dip0)
        clean = abs(nd) < CLEAN_NORM and abs(dip - dip0) < CLEAN_DIP_DEG
        s[S_CLEAN4] = _ema(s[S_CLEAN4], 1.0 if clean else 0.0, dt / 4.0)
        s[S_ND2] = _ema(s[S_ND2], nd, dt / 2.0)
        s[S_DD2] = _ema(s[S_DD2], dip - dip0, dt / 2.0)
        g, g0 = inputs.gyr[i], inputs.gyr[i - 1 if i > 0 else 0]
        s[S_G1] = _ema(s[S_G1], norm3(g), dt)
        a = inputs.acc[i]
        s[S_ACC05] = _ema(s[S_ACC05], abs(norm3(a) - GRAVITY) / GRAVITY, dt / 0.5)
        s[S_SPR1] = _ema(s[S_SPR1], spread[i], dt)
        turn = from_rotvec1(0.5 * (g0 + g) * dt)  # the filter's gyro prediction without bias (eq. 17)
        if clean:
            s[S_MHC] = _ema(s[S_MHC], mh, dt / 2.0)
            s[S_TCLEAN] = 0.0
            s[Q_ANC : Q_ANC + 4] = q
        else:
            s[S_TCLEAN] += dt
            s[Q_ANC : Q_ANC + 4] = normalize1(mul1(s[Q_ANC : Q_ANC + 4].copy(), turn))
        sig = out.sig[i]
        if sig[SIGNAL.qsf_active] > 0.5 and sig[SIGNAL.age] > 0.0:
            s[Q_PER : Q_PER + 4] = normalize1(mul1(s[Q_PER : Q_PER + 4].copy(), turn))
            s[S_INN1] = _ema(s[S_INN1], sig[SIGNAL.innov_norm] / sigma_m, dt)
        else:
            s[Q_PER : Q_PER + 4] = q
    if state.period_active[0]:
        s[S_REFH] = wrap_deg(
            planar_heading(rotate1(out.q[stop - 1], inputs.mag[stop - 1])) - planar_heading(state.mag_ref)
        )
    else:
        s[S_REFH] = 0.0
    s[S_REF05] = _ema(s[S_REF05], s[S_REFH], min((stop - start) * dt / 0.5, 1.0))
    q = out.q[stop - 1]
    qw, qx, qy, qz = q[0], q[1], q[2], q[3]
    val[X.mh_ema_1], val[X.mh_ema_4], val[X.mh_ema_16] = s[S_MH1], s[S_MH4], s[S_MH16]
    val[X.mh_clean], val[X.clean_ema_4], val[X.t_clean] = s[S_MHC], s[S_CLEAN4], s[S_TCLEAN] / 10.0
    val[X.d_anchor] = _heading(qw, qx, qy, qz, s[Q_ANC], s[Q_ANC + 1], s[Q_ANC + 2], s[Q_ANC + 3])
    val[X.d_period] = _heading(qw, qx, qy, qz, s[Q_PER], s[Q_PER + 1], s[Q_PER + 2], s[Q_PER + 3])
    val[X.ref_h], val[X.ref_h_ema_05] = s[S_REFH], s[S_REF05]
    val[X.spread_ema_1], val[X.innov_ema_1] = s[S_SPR1], s[S_INN1]
    val[X.nd_ema_2], val[X.dd_ema_2], val[X.gyro_ema_1], val[X.acc_ema_05] = s[S_ND2], s[S_DD2], s[S_G1], s[S_ACC05]
    for k in range(val.shape[0]):
        val[k] = min(max(val[k], _LOW[k]), _HIGH[k])
