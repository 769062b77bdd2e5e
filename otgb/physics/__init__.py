"""Simulators: the incomplete physics f_p and the data-generating process built from it."""

from otgb.physics.base import PhysicsModel, SimulationDiverged, Term
from otgb.physics.pendulum import Pendulum
from otgb.physics.priors import Choice, Constant, Prior, Uniform
from otgb.physics.terms import ViscousFriction

__all__ = [
    "Choice",
    "Constant",
    "Pendulum",
    "PhysicsModel",
    "Prior",
    "SimulationDiverged",
    "Term",
    "Uniform",
    "ViscousFriction",
]
