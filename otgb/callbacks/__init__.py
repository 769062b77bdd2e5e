"""Lightning callbacks: the joint evaluation and figures."""

from otgb.callbacks.evaluation import JointEvaluation
from otgb.callbacks.figures import FieldFigure, TrajectoryFigure

__all__ = ["FieldFigure", "JointEvaluation", "TrajectoryFigure"]
