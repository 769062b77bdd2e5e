"""Lightning callbacks: the joint evaluation and figures."""

from otgb.callbacks.evaluation import JointEvaluation
from otgb.callbacks.figures import TrajectoryFigure

__all__ = ["JointEvaluation", "TrajectoryFigure"]
