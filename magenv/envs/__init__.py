"""Gymnasium environments of magenv (each class docstring documents its observation, action and reward).

* ``blend.MagBlendEnv`` — ``magenv/MagBlend-v0``: the weight λ of the IMU filter
  in Fan et al.'s IMU/MIMU Madgwick blend.
* ``kalman.MagKalmanEnv`` — ``magenv/MagKalman-v0``: the gain multiplier γ of the
  magnetometer update in a quaternion Kalman filter.
* ``constraint.MagConstraintEnv`` — ``magenv/MagConstraint-v0``: the weight w of the
  magnetometer against the two-link joint constraint (Jung & Lee 2019).
* ``common`` — pieces every env shares (trial sources, argument and action checks,
  the Python-loop vector env).
"""
