"""Lightning callbacks: the evaluation, figures and the grey-box's component analysis (computed in :mod:`otgb.analysis`)."""

from otgb.callbacks.components import ComponentAnalysis
from otgb.callbacks.evaluation import Evaluation
from otgb.callbacks.figures import FieldFigure, TrajectoryFigure

__all__ = ["ComponentAnalysis", "Evaluation", "FieldFigure", "TrajectoryFigure"]
