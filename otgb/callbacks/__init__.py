"""Lightning callbacks: figures."""

from otgb.callbacks.figures import TrajectoryFigure

__all__ = ["TrajectoryFigure"]
