"""Data: the source stream, measured data and joint evaluation sets."""

from otgb.data.datamodule import JointDataset, SimulationDataModule
from otgb.data.measured import check_trajectories, generate_joint, generate_measured, load_measured
from otgb.data.stream import SourceStream

__all__ = [
    "JointDataset",
    "SimulationDataModule",
    "SourceStream",
    "check_trajectories",
    "generate_joint",
    "generate_measured",
    "load_measured",
]
