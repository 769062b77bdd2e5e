"""Missing-effect discovery: locate, name, add and verify what f_p lacks (``otgb discover``).

From Python: :class:`MissingEffect` (``fit``, then ``verdict_``, ``terms_``, ``augmented_physics_``, ``report_``).
"""

from otgb.discovery.api import MissingEffect

__all__ = ["MissingEffect"]
