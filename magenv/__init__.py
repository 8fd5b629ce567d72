"""magenv: Gymnasium environments in which a policy learns how far to trust a magnetometer.

Importing ``magenv`` registers its environments under the ``magenv/``
namespace, e.g. ``gymnasium.make("magenv/MagBlend-v0")``; their ids and classes
are the one table ``magenv.envs.ENVS``, each documented in its class docstring.

``magenv.TrustFilter`` (``magenv.streaming``, imported on first use) runs any method on your own IMU data,
sample by sample or on whole arrays.
"""

__version__ = "0.1.0"


from magenv.envs import register_all

register_all()


def __getattr__(name: str):
    """``magenv.TrustFilter``: imported on first use (it loads the method registry)."""
    if name == "TrustFilter":
        from magenv.streaming import TrustFilter

        return TrustFilter
    raise AttributeError(f"module 'magenv' has no attribute {name!r}")
