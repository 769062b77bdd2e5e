"""Data: the source stream, measured data (generated or from a file) and evaluation sets."""

from otgb.data.datamodule import JointDataset, SimulationDataModule
from otgb.data.files import MeasuredFile, check_trajectories, read_measured
from otgb.data.measured import generate_joint, generate_measured, split_indices
from otgb.data.stream import SourceStream

__all__ = [
    "JointDataset",
    "MeasuredFile",
    "SimulationDataModule",
    "SourceStream",
    "check_trajectories",
    "generate_joint",
    "generate_measured",
    "read_measured",
    "split_indices",
]
