import pytest
import torch

from otgb.physics import Constant, Pendulum, ViscousFriction


@pytest.fixture
def pendulum() -> Pendulum:
    return Pendulum()


@pytest.fixture
def damped(pendulum: Pendulum) -> Pendulum:
    return pendulum.with_hidden_effect([ViscousFriction(Constant(1.2))])


@pytest.fixture
def generator() -> torch.Generator:
    return torch.Generator().manual_seed(0)
