"""magenv: Gymnasium environments in which a policy learns how far to trust a magnetometer.

Importing ``magenv`` registers its environments under the ``magenv/``
namespace, e.g. ``gymnasium.make("magenv/MagBlend-v0")``:

* ``magenv/MagBlend-v0`` — ``magenv.envs.blend.MagBlendEnv``: the action is the
  weight λ of the IMU filter in Fan et al.'s IMU/MIMU Madgwick blend.
"""

__version__ = "0.1.0"


def _register_envs() -> None:
    from gymnasium.envs.registration import register, registry

    if "magenv/MagBlend-v0" not in registry:
        register(id="magenv/MagBlend-v0", entry_point="magenv.envs.blend:MagBlendEnv",
                 vector_entry_point="magenv.envs.blend:MagBlendVectorEnv")


_register_envs()
