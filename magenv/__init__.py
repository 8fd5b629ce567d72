"""magenv: Gymnasium environments in which a policy learns how far to trust a magnetometer.

Importing ``magenv`` registers its environments under the ``magenv/``
namespace, e.g. ``gymnasium.make("magenv/MagBlend-v0")``; their ids and classes
are the one table ``magenv.envs.ENVS``, each documented in its class docstring.

``magenv.streaming.TrustFilter`` runs any method on your own IMU data, sample by sample or on whole arrays.
"""

__version__ = "0.1.0"


from magenv.envs import register_all

register_all()
