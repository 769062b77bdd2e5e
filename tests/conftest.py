import os
import signal

import pytest
import torch
from lightning import Callback

from otgb.physics import Constant, Pendulum, ViscousFriction


def pytest_configure(config) -> None:
    """Under pytest-xdist each worker computes on its share of the cores, and so do the commands a test starts:
    torch's default of one thread per core in every worker would put more threads than cores on the machine."""
    workers = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
    if workers > 1:
        cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
        threads = max(1, cores // workers)
        os.environ["OMP_NUM_THREADS"] = str(threads)
        torch.set_num_threads(threads)


@pytest.fixture
def pendulum() -> Pendulum:
    return Pendulum()


@pytest.fixture
def damped(pendulum: Pendulum) -> Pendulum:
    return pendulum.with_hidden_effect([ViscousFriction(Constant(1.2))])


@pytest.fixture
def generator() -> torch.Generator:
    return torch.Generator().manual_seed(0)


class StopAt(Callback):
    """Stops training after ``step`` training steps, like an interrupted run."""

    def __init__(self, step: int) -> None:
        self.step = step

    def on_train_batch_end(self, trainer, *args) -> None:
        if trainer.global_step >= self.step:
            trainer.should_stop = True


class RecordSources(Callback):
    """Saves the source inputs (x0) each process trained on to ``<folder>/sources_rank<r>.pt``."""

    def __init__(self, folder: str) -> None:
        self.folder, self.x0 = folder, []

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:
        self.x0.append(batch["x0"].flatten(0, 1).cpu())

    def on_train_end(self, trainer, pl_module) -> None:
        torch.save(torch.cat(self.x0), f"{self.folder}/sources_rank{trainer.global_rank}.pt")


class PoisonSources(Callback):
    """Sets the initial states of map update ``k`` at training step ``step`` to NaN: that update's solve fails."""

    def __init__(self, step: int, k: int = 0) -> None:
        self.step, self.k = step, k

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx) -> None:
        if trainer.global_step == self.step:
            batch["x0"][self.k] = float("nan")


class SendSigterm(Callback):
    """Sends SIGTERM to this process after training step ``step``, as a scheduler ending a job would
    (under several processes: only the process of global rank ``rank``, if given)."""

    def __init__(self, step: int, rank: int | None = None) -> None:
        self.step, self.rank = step, rank

    def on_train_batch_end(self, trainer, *args) -> None:
        if trainer.global_step == self.step and self.rank in (None, trainer.global_rank):
            os.kill(os.getpid(), signal.SIGTERM)


@pytest.fixture(autouse=True)
def default_solver():
    """Each test starts on the default solve path with no solves counted (``auto`` compiles after a count)."""
    from otgb.physics import solvers

    solvers.reset()
    yield
    solvers.reset()
