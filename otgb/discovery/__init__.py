"""Missing-effect discovery: locate, name, add and verify what f_p lacks (``otgb discover``).

From Python: :class:`MissingEffect` (``MissingEffect.from_config(path, overrides)`` or ``MissingEffect(physics)``),
whose ``fit(measurements)`` returns a :class:`DiscoveryResult` (``verdict``, ``terms``, ``augmented_physics``,
``print()``, ``write(dir)``).
"""

from otgb.discovery.api import MissingEffect
from otgb.discovery.result import DiscoveryResult, NamedTerm

__all__ = ["DiscoveryResult", "MissingEffect", "NamedTerm"]
