"""Gymnasium environments of magenv (each class docstring documents its observation, action and reward).

* ``blend.MagBlendEnv`` — ``magenv/MagBlend-v0``: the weight λ of the IMU filter
  in Fan et al.'s IMU/MIMU Madgwick blend.
* ``kalman.MagKalmanEnv`` — ``magenv/MagKalman-v0``: the gain multiplier γ of the
  magnetometer update in a quaternion Kalman filter.
* ``constraint.MagConstraintEnv`` — ``magenv/MagConstraint-v0``: the weight w of the
  magnetometer against the two-link joint constraint (Jung & Lee 2019).
* ``qsf.MagQSFEnv`` — ``magenv/MagQSF-v0``: when to start a quasi-static-field
  period, keep its reference or skip the magnetic update, and how much to trust it
  (Combettes & Renaudin 2016).
* ``vqf.MagVQFEnv`` — ``magenv/MagVQF-v0``: the trust u of VQF's magnetometer correction (Laidig & Seel
  2023), with VQF's own disturbance rejection off (replaced) or on.
* ``common`` — pieces every env shares (trial sources, argument and action checks,
  the vector env).

``ENVS`` is the one table of their ids and classes; ``magenv`` registers them
with Gymnasium on import, without importing the env modules themselves.
"""

BLEND_ID = "magenv/MagBlend-v0"
KALMAN_ID = "magenv/MagKalman-v0"
CONSTRAINT_ID = "magenv/MagConstraint-v0"
QSF_ID = "magenv/MagQSF-v0"
VQF_ID = "magenv/MagVQF-v0"

#: env id → (entry point, vector entry point)
ENVS = {
    BLEND_ID: ("magenv.envs.blend:MagBlendEnv", "magenv.envs.blend:MagBlendVectorEnv"),
    KALMAN_ID: ("magenv.envs.kalman:MagKalmanEnv", "magenv.envs.kalman:MagKalmanVectorEnv"),
    CONSTRAINT_ID: ("magenv.envs.constraint:MagConstraintEnv", "magenv.envs.constraint:MagConstraintVectorEnv"),
    QSF_ID: ("magenv.envs.qsf:MagQSFEnv", "magenv.envs.qsf:MagQSFVectorEnv"),
    VQF_ID: ("magenv.envs.vqf:MagVQFEnv", "magenv.envs.vqf:MagVQFVectorEnv"),
}


def register_all() -> None:
    """Register every env of ``ENVS`` with Gymnasium (once)."""
    from gymnasium.envs.registration import register, registry

    for env_id, (entry, vector_entry) in ENVS.items():
        if env_id not in registry:
            register(id=env_id, entry_point=entry, vector_entry_point=vector_entry)
