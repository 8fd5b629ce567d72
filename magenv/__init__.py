"""magenv: Gymnasium environments in which a policy learns how far to trust a magnetometer.

Importing ``magenv`` registers its environments under the ``magenv/``
namespace, e.g. ``gymnasium.make("magenv/MagBlend-v0")``.
"""

__version__ = "0.1.0"
