"""Lightning callbacks: the joint evaluation and figures."""

from otgb.callbacks.evaluation import Evaluation
from otgb.callbacks.figures import FieldFigure, TrajectoryFigure

__all__ = ["Evaluation", "FieldFigure", "TrajectoryFigure"]
