"""Simulators: the incomplete physics f_p and the data-generating process built from it."""

from otgb.physics.advection_diffusion import AdvectionDiffusion
from otgb.physics.augmented import Augmented
from otgb.physics.base import FieldModel, PhysicsModel, SimulationDiverged, Term, raise_if_diverged
from otgb.physics.pendulum import Pendulum
from otgb.physics.priors import Choice, Constant, Normal, Prior, Uniform
from otgb.physics.reaction_diffusion import ReactionDiffusion
from otgb.physics.signals import InputProcess, Recorded, SumOfSines
from otgb.physics.solvers import SOLVERS, set_solver
from otgb.physics.terms import Advection, ConstantDrain, FitzHughNagumoReaction, FormTerm, LibraryTerm, ViscousFriction

__all__ = [
    "Advection",
    "AdvectionDiffusion",
    "Augmented",
    "ConstantDrain",
    "FieldModel",
    "FitzHughNagumoReaction",
    "FormTerm",
    "InputProcess",
    "LibraryTerm",
    "Normal",
    "ReactionDiffusion",
    "Recorded",
    "SumOfSines",
    "SOLVERS",
    "set_solver",
    "Choice",
    "Constant",
    "Pendulum",
    "PhysicsModel",
    "Prior",
    "SimulationDiverged",
    "Term",
    "Uniform",
    "raise_if_diverged",
    "ViscousFriction",
]
