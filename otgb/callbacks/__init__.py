"""Lightning callbacks: the joint evaluation, figures and the grey-box's component analysis."""

from otgb.callbacks.components import ComponentAnalysis, component_analysis
from otgb.callbacks.evaluation import Evaluation
from otgb.callbacks.figures import FieldFigure, TrajectoryFigure

__all__ = ["ComponentAnalysis", "Evaluation", "FieldFigure", "TrajectoryFigure", "component_analysis"]
