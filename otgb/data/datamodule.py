"""The data module: source stream, fixed measured set, joint validation and test sets."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import torch
from lightning import LightningDataModule
from torch import Tensor
from torch.utils.data import DataLoader, Dataset

from otgb.data.measured import cache_key, cached, generate_joint, generate_measured, load_measured
from otgb.data.stream import SourceStream
from otgb.physics.base import PhysicsModel, Term

CACHE_FORMAT = 2  # 2: joint sets hold y_ref


class JointDataset(Dataset):
    """Rows of a joint set: dicts of x0, theta, x, y (M draws) and y_ref (M more DGP draws)."""

    def __init__(self, tensors: dict[str, Tensor]) -> None:
        self.tensors = tensors

    def __len__(self) -> int:
        return len(self.tensors["x0"])

    def __getitem__(self, i: int) -> dict[str, Tensor]:
        return {k: v[i] for k, v in self.tensors.items()}


class SimulationDataModule(LightningDataModule):
    """Source simulations of f_p on the fly, next to a fixed set of measured trajectories.

    The DGP is ``physics`` with ``hidden_effect`` added (optionally with a finer solver step,
    ``measured_step_size``). Training batches are items of :class:`SourceStream`; f_p is
    simulated on the training device when a batch arrives there, and the simulations are
    counted against ``simulation_budget`` (over all ranks). Validation and test sets are
    joint: the same (x0, theta) through f_p and, ``draws_per_input`` times, through the DGP.

    Args:
        physics: the incomplete model f_p.
        hidden_effect: the terms the DGP adds to f_p (hidden from the model).
        batch_size: source inputs per map update.
        measured_batch_size: measured trajectories per critic update (default: batch_size).
        batches_per_step: map updates per critic update (T_max; linked from the model).
        simulation_budget: total f_p simulations for training.
        n_measured: |Y| when the measured set is generated from the DGP.
        measured_path: a user's measured set (.pt/.npz, key "y", shape (N, T, *obs)) instead.
        n_val, n_test: joint inputs for validation and test. draws_per_input: M.
        seed: seed of the generated sets. stream_seed: seed of the source stream
            (default: the run's seed, ``torch.initial_seed()`` after ``seed_everything``).
        cache_dir: where generated sets are cached.
    """

    def __init__(
        self,
        physics: PhysicsModel,
        hidden_effect: Sequence[Term] = (),
        batch_size: int = 64,
        measured_batch_size: int | None = None,
        batches_per_step: int = 1,
        simulation_budget: int = 1_000_000,
        n_measured: int = 1000,
        measured_path: str | None = None,
        measured_step_size: float | None = None,
        n_val: int = 200,
        n_test: int = 300,
        draws_per_input: int = 1,
        eval_batch_size: int = 256,
        seed: int = 0,
        stream_seed: int | None = None,
        cache_dir: str = "data",
        num_workers: int = 0,
    ) -> None:
        super().__init__()
        measured_batch_size = batch_size if measured_batch_size is None else measured_batch_size
        for name, value in [
            ("batch_size", batch_size),
            ("measured_batch_size", measured_batch_size),
            ("batches_per_step", batches_per_step),
            ("n_val", n_val),
            ("n_test", n_test),
            ("draws_per_input", draws_per_input),
            ("eval_batch_size", eval_batch_size),
            ("n_measured", n_measured),
        ]:
            if value < 1:
                raise ValueError(f"data.{name} must be >= 1, got {value}")
        if simulation_budget < batch_size * batches_per_step:
            raise ValueError(
                f"data.simulation_budget={simulation_budget} is smaller than one training step needs "
                f"(batch_size * batches_per_step = {batch_size * batches_per_step})"
            )
        self.physics = physics
        self.dgp = physics.with_hidden_effect(hidden_effect, step_size=measured_step_size)
        self.batch_size, self.batches_per_step = batch_size, batches_per_step
        self.measured_batch_size = measured_batch_size
        self.simulation_budget = simulation_budget
        self.n_measured, self.measured_path = n_measured, measured_path
        self.n_val, self.n_test, self.draws_per_input = n_val, n_test, draws_per_input
        self.eval_batch_size, self.seed, self.stream_seed = eval_batch_size, seed, stream_seed
        self.cache_dir, self.num_workers = cache_dir, num_workers
        self.items_consumed = 0
        self.measured: Tensor | None = None
        self.val_set: dict[str, Tensor] | None = None
        self.test_set: dict[str, Tensor] | None = None

    # --- sets ---------------------------------------------------------------------------
    def setup(self, stage: str) -> None:
        if stage == "fit" and self.measured is None:
            self.measured = self._measured_set()
        if stage in ("fit", "validate") and self.val_set is None:
            self.val_set = self._joint_set("val", self.n_val)
        if stage == "test" and self.test_set is None:
            self.test_set = self._joint_set("test", self.n_test)
        if self.stream_seed is None:
            self.stream_seed = torch.initial_seed()

    def _key(self, *parts: object) -> str:
        return cache_key(CACHE_FORMAT, repr(self.physics), repr(self.dgp), self.seed, *parts)

    def _measured_set(self) -> Tensor:
        if self.measured_path is not None:
            return load_measured(self.measured_path, self.physics.trajectory_shape)
        key = self._key("measured", self.n_measured)
        return cached(self.cache_dir, "measured", key, lambda: {"y": generate_measured(self.dgp, self.n_measured, self.seed)})[
            "y"
        ]

    def _joint_set(self, split: str, n: int) -> dict[str, Tensor]:
        key = self._key(split, n, self.draws_per_input)
        return cached(
            self.cache_dir, split, key, lambda: generate_joint(self.physics, self.dgp, n, self.draws_per_input, self.seed, split)
        )

    # --- loaders ------------------------------------------------------------------------
    def source_stream(self) -> SourceStream:
        world = self.trainer.world_size if self.trainer is not None else 1
        rank = self.trainer.global_rank if self.trainer is not None else 0
        return SourceStream(
            self.physics,
            self.measured,
            self.batch_size,
            self.batches_per_step,
            self.measured_batch_size,
            budget=self.simulation_budget // world,
            seed=self.stream_seed,
            rank=rank,
            start=self.items_consumed,
        )

    def train_dataloader(self) -> DataLoader:
        return DataLoader(self.source_stream(), batch_size=None, num_workers=self.num_workers)

    def val_dataloader(self) -> DataLoader:
        return DataLoader(JointDataset(self.val_set), batch_size=self.eval_batch_size, shuffle=False)

    def test_dataloader(self) -> DataLoader:
        return DataLoader(JointDataset(self.test_set), batch_size=self.eval_batch_size, shuffle=False)

    # --- on-device simulation and the budget ------------------------------------------
    def on_after_batch_transfer(self, batch: Any, dataloader_idx: int) -> Any:
        """Simulate f_p for a training item on the device it landed on, and count it."""
        if not (isinstance(batch, dict) and "index" in batch and "x" not in batch):
            return batch
        x0, theta = batch["x0"], batch["theta"]
        with torch.no_grad():
            x = self.physics.simulate(x0.flatten(0, 1), theta.flatten(0, 1))
        batch["x"] = x.reshape(*x0.shape[:2], *x.shape[1:])
        self.items_consumed = int(batch["index"]) + 1
        return batch

    @property
    def selection_metric(self) -> str:
        """The validation metric ``checkpoint.monitor: auto`` selects on: pointwise error one-to-one, else MMD."""
        return "val/abs_err" if not self.dgp.is_stochastic else "val/mmd"

    @property
    def simulations(self) -> int:
        """f_p simulations spent on training so far, over all ranks."""
        world = self.trainer.world_size if self.trainer is not None else 1
        return self.items_consumed * self.batch_size * self.batches_per_step * world

    def state_dict(self) -> dict[str, Any]:
        return {"items_consumed": self.items_consumed, "stream_seed": self.stream_seed}

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        self.items_consumed = int(state_dict["items_consumed"])
        self.stream_seed = state_dict["stream_seed"]
