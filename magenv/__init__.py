"""magenv: Gymnasium environments in which a policy learns how far to trust a magnetometer.

Importing ``magenv`` registers its environments under the ``magenv/``
namespace, e.g. ``gymnasium.make("magenv/MagBlend-v0")``:

* ``magenv/MagBlend-v0`` — ``magenv.envs.blend.MagBlendEnv``: the action is the
  weight λ of the IMU filter in Fan et al.'s IMU/MIMU Madgwick blend.
* ``magenv/MagKalman-v0`` — ``magenv.envs.kalman.MagKalmanEnv``: the gain γ of the
  magnetometer update in a quaternion Kalman filter.
* ``magenv/MagConstraint-v0`` — ``magenv.envs.constraint.MagConstraintEnv``: the weight w
  of the magnetometer against a two-link kinematic constraint (Jung & Lee 2019).
* ``magenv/MagQSF-v0`` — ``magenv.envs.qsf.MagQSFEnv``: when to start a quasi-static-field
  period, keep its reference or skip the magnetic update, and how much to trust it
  (Combettes & Renaudin 2016).
"""

__version__ = "0.1.0"


from magenv.envs import register_all

register_all()
