"""Gymnasium environments of magenv.

* ``blend.MagBlendEnv`` — ``magenv/MagBlend-v0``: the action is the weight λ
  of the IMU filter in Fan et al.'s IMU/MIMU Madgwick blend (class docstring:
  observation table, reward, options); ``blend.MagBlendVectorEnv`` is its
  ``vector_entry_point``.
"""
