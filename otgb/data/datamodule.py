"""The data module: source stream, measured set, and validation/test sets in joint or marginal mode."""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from typing import Any

import torch
from lightning import LightningDataModule
from lightning.pytorch.overrides.distributed import UnrepeatedDistributedSampler
from lightning.pytorch.utilities import rank_zero_info, rank_zero_only
from torch import Tensor
from torch.utils.data import DataLoader, Dataset

from otgb.data.sources import FileMeasurements, GeneratedMeasurements, MeasurementSource
from otgb.data.stream import SourceStream, StreamLoader
from otgb.errors import InputError
from otgb.physics.base import PhysicsModel, Term

log = logging.getLogger("otgb.data")  # a warning prints as its one line


class JointDataset(Dataset):
    """Rows of an evaluation set: dicts of x0, theta, x, y (M draws) and, when joint, y_ref (M more DGP draws)."""

    def __init__(self, tensors: dict[str, Tensor]) -> None:
        self.tensors = tensors

    def __len__(self) -> int:
        return len(self.tensors["x0"])

    def __getitem__(self, i: int) -> dict[str, Tensor]:
        return {k: v[i] for k, v in self.tensors.items()}


class SimulationDataModule(LightningDataModule):
    """Source simulations of f_p on the fly, next to a fixed set of measured trajectories.

    Training batches are items of :class:`SourceStream`; f_p is simulated on the training
    device when a batch arrives there, and the simulations are counted against
    ``simulation_budget`` (over all ranks). The measured data and the evaluation come in one
    of two modes (:attr:`mode`, named in the log at start-up and in every test report):

    - ``"joint"`` (``hidden_effect`` given, no file): the DGP is known, ``physics`` plus the
      hidden-effect terms (optionally with a finer solver step, ``measured_step_size``). The
      measured set is generated from it; validation and test sets are joint: the same
      (x0, theta) through f_p and, ``draws_per_input`` times, through the DGP.
    - ``"marginal"`` (``measured_path`` given): the measurements are all there is. The file
      (:mod:`otgb.data.files`) is split into train / validation / test parts that never
      overlap; the critic sees only the train part. A validation or test set holds the
      held-out measurements and, for the map and f_p, as many inputs (x0, theta) drawn from
      the priors, or the inputs the file recorded for each trajectory.

    Args:
        physics: The incomplete model f_p, a :class:`otgb.physics.PhysicsModel`.
        hidden_effect: Terms the data-generating process adds to f_p, hidden from the model (joint mode).
        batch_size: Source inputs per map update.
        measured_batch_size: Measured trajectories per critic update (default: batch_size).
        batches_per_step: Source batches per training step: one per map update and one per critic update
            after the first (linked from the model: t_max + critic_steps - 1).
        measured_batches_per_step: Measured batches per training step, one per critic update (linked from
            the model's critic_steps).
        simulation_budget: Total f_p simulations for training; training stops when it is spent.
        n_measured: Size |Y| of the generated measured set (joint mode).
        measured_path: A file of measured trajectories (.pt, .npz or .csv): selects the marginal mode.
        measured_step_size: Solver step of the generated measured data (joint mode; default: the model's).
        val_fraction: Share of the file's trajectories held out for validation (marginal mode).
        test_fraction: Share of the file's trajectories held out for the test (marginal mode).
        measurement_noise: Standard deviation of the white noise on every value of the file's measurements, in
            their units (marginal mode; 0: noise-free). The model's outputs and f_p's get as much wherever they
            are compared with the measurements (the critic, the marginal metrics, discovery), so that the noise is
            neither learned by the map nor read as a disagreement.
        n_val: Joint validation inputs generated from the DGP (joint mode).
        n_test: Joint test inputs generated from the DGP (joint mode).
        draws_per_input: DGP draws M per joint validation/test input (joint mode).
        eval_batch_size: Inputs per validation/test batch.
        seed: Seed of the generated sets, the split of a file and the evaluation inputs.
        stream_seed: Seed of the source stream (default: the run's seed after seed_everything).
        cache_dir: Folder where generated sets are cached.
        num_workers: DataLoader workers for the source stream.
    """

    def __init__(
        self,
        physics: PhysicsModel,
        hidden_effect: Sequence[Term] = (),
        batch_size: int = 64,
        measured_batch_size: int | None = None,
        batches_per_step: int = 1,
        measured_batches_per_step: int = 1,
        simulation_budget: int = 1_000_000,
        n_measured: int = 1000,
        measured_path: str | None = None,
        measured_step_size: float | None = None,
        val_fraction: float = 0.15,
        test_fraction: float = 0.15,
        measurement_noise: float = 0.0,
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
            ("measured_batches_per_step", measured_batches_per_step),
            ("n_val", n_val),
            ("n_test", n_test),
            ("draws_per_input", draws_per_input),
            ("eval_batch_size", eval_batch_size),
            ("n_measured", n_measured),
        ]:
            if value < 1:
                raise InputError(f"data.{name} must be >= 1, got {value}")
        if simulation_budget < batch_size * batches_per_step:
            raise InputError(
                f"data.simulation_budget={simulation_budget} is smaller than one training step needs "
                f"(batch_size * batches_per_step = {batch_size * batches_per_step})"
            )
        if measured_path is not None and hidden_effect:
            raise InputError(
                f"data.measured_path={measured_path!r} and data.hidden_effect are both set: measurements from a file need no "
                "hidden effect (it only generates synthetic measurements); remove one, e.g. --data.hidden_effect=[]"
            )
        check_measurement_noise(measurement_noise, measured_path)
        if measured_path is None and not hidden_effect:
            raise InputError(
                "data: no measured data: set data.measured_path to a file of measurements, or data.hidden_effect to the "
                "terms that generate synthetic measurements from physics + terms"
            )
        self.batch_size, self.batches_per_step = batch_size, batches_per_step
        self.measured_batch_size, self.measured_batches_per_step = measured_batch_size, measured_batches_per_step
        self.simulation_budget = simulation_budget
        self.n_measured, self.measured_path = n_measured, measured_path
        self.n_val, self.n_test, self.draws_per_input = n_val, n_test, draws_per_input
        self.eval_batch_size, self.seed, self.stream_seed = eval_batch_size, seed, stream_seed
        self.cache_dir, self.num_workers = cache_dir, num_workers
        self.items_consumed = 0
        self.trained_on: str | None = None  # the measurements a loaded checkpoint was trained on, where not these
        self.measured: Tensor | None = None
        self.val_set: dict[str, Tensor] | None = None
        self.test_set: dict[str, Tensor] | None = None
        self.source: MeasurementSource = (
            GeneratedMeasurements(physics, list(hidden_effect), n_measured, draws_per_input, seed, cache_dir, measured_step_size)
            if measured_path is None
            else FileMeasurements(physics, measured_path, val_fraction, test_fraction, seed, measurement_noise)
        )
        self.physics = self.source.physics  # f_p, read at the file's own times where they are not its grid
        self._announced = False  # whether the evaluation mode has been logged (at the first setup, once the model is built)

    # --- the source of the measurements ----------------------------------------------------
    @property
    def measurement_noise(self) -> float:
        """The standard deviation of the noise on the measured values (0: noise-free)."""
        return self.source.measurement_noise

    @property
    def mode(self) -> str:
        """ "joint" (a known DGP generates the measured data) or "marginal" (measurements from a file)."""
        return self.source.mode

    @property
    def dgp(self) -> PhysicsModel | None:
        """The data-generating process, where one is configured."""
        return getattr(self.source, "dgp", None)

    @property
    def recorded_inputs(self) -> tuple[str, ...]:
        """Map inputs recorded with each measured trajectory: a subset of ("theta", "x0"); all of them when joint."""
        return self.source.recorded_inputs

    def describe(self) -> str:
        """What the evaluation compares, in one sentence (logged at start-up, written in reports)."""
        return self.source.describe()

    # --- sets ---------------------------------------------------------------------------
    def setup(self, stage: str) -> None:
        if not self._announced:
            rank_zero_info(f"otgb: evaluation mode '{self.mode}': {self.describe()}")
            self._announced = True
        if stage == "fit" and self.measured is None:
            self.measured = self._measured_set()
        if stage in ("fit", "validate") and self.val_set is None:
            self.val_set = self._evaluation_set("val", self.n_val)
        if stage == "test" and self.test_set is None:
            self.test_set = self._evaluation_set("test", self.n_test)
        if self.stream_seed is None:
            self.stream_seed = torch.initial_seed()

    def _measured_set(self) -> Tensor:
        return self.source.measured_set()

    def _evaluation_set(self, split: str, n: int) -> dict[str, Tensor]:
        return self.source.evaluation_set(split, n)

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
            self.measured_batches_per_step,
            budget=self.simulation_budget // world,
            seed=self.stream_seed,
            rank=rank,
            start=self.items_consumed,
        )

    def train_dataloader(self) -> DataLoader:
        return StreamLoader(self.source_stream(), lambda: self.items_consumed, num_workers=self.num_workers)

    def val_dataloader(self) -> DataLoader:
        return self._evaluation_loader(self.val_set, "validation")

    def test_dataloader(self) -> DataLoader:
        return self._evaluation_loader(self.test_set, "test")

    def _evaluation_loader(self, tensors: dict[str, Tensor], split: str) -> DataLoader:
        """Each evaluation input once over all processes: Lightning's default distributed sampler would pad the
        processes' shares to one length with repeated inputs, which the synced metrics would then count twice."""
        dataset, world = JointDataset(tensors), self.trainer.world_size if self.trainer is not None else 1
        if len(dataset) < world:
            raise InputError(f"the {split} set has {len(dataset)} inputs for {world} processes; expected at least one each")
        sampler = None if world <= 1 else UnrepeatedDistributedSampler(dataset, world, self.trainer.global_rank, shuffle=False)
        return DataLoader(dataset, batch_size=self.eval_batch_size, sampler=sampler)

    # --- on-device simulation and the budget ------------------------------------------
    def on_after_batch_transfer(self, batch: Any, dataloader_idx: int) -> Any:
        """Simulate f_p for a training item on the device it landed on, and count it."""
        if not (isinstance(batch, dict) and "index" in batch and "x" not in batch):
            return batch
        x0, theta, signals = batch["x0"], batch["theta"], batch.get("signals")
        with torch.no_grad():
            x = self.physics.simulate(
                x0.flatten(0, 1), theta.flatten(0, 1), signals=None if signals is None else signals.flatten(0, 1)
            )
        batch["x"] = x.reshape(*x0.shape[:2], *x.shape[1:])
        self.items_consumed = int(batch["index"]) + 1
        return batch

    @property
    def selection_metric(self) -> str:
        """The validation metric ``checkpoint.monitor: auto`` selects on: the pointwise error against a deterministic
        process, the MMD against a stochastic one, the energy distance to held-out measurements from a file."""
        return self.source.selection_metric

    @property
    def simulations(self) -> int:
        """f_p simulations spent on training so far, over all ranks."""
        world = self.trainer.world_size if self.trainer is not None else 1
        return self.items_consumed * self.batch_size * self.batches_per_step * world

    def state_dict(self) -> dict[str, Any]:
        return {"items_consumed": self.items_consumed, "stream_seed": self.stream_seed, "measurements": self.source.identity}

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        self.items_consumed = int(state_dict["items_consumed"])
        self.stream_seed = state_dict["stream_seed"]
        self.compare_with_training(state_dict)

    def compare_with_training(self, state_dict: dict[str, Any]) -> None:
        """Warn, once, where the checkpoint whose datamodule state is ``state_dict`` was trained on other measurements
        than this run's; :attr:`trained_on` then names them (the reports say it beside the figures)."""
        saved = state_dict.get("measurements")  # older checkpoints hold none: nothing to compare
        if saved is None or saved["key"] == self.source.identity["key"] or self.trained_on is not None:
            return
        now, resplit = self.source.identity["what"], saved.get("data") == self.source.identity["data"]
        self.trained_on = saved["what"] + (", split differently" if resplit else "")
        if resplit:
            consequence = (
                "split differently (data.seed, data.val_fraction or data.test_fraction): its held-out parts may hold "
                "trajectories the map trained on"
            )
        else:
            other = " (with other settings)" if saved["what"] == now else ""
            consequence = f"this run uses {now}{other}: its figures score the map on data it was not trained for"
        rank_zero_only(log.warning)(
            f"otgb: the checkpoint was trained on {saved['what']}; {consequence} (give the fit's data settings to "
            "evaluate it on its own)"
        )


def check_measurement_noise(sd: float, measured_path: str | None) -> None:
    """A standard deviation >= 0, and above 0 only for measurements from a file."""
    if not (isinstance(sd, (int, float)) and math.isfinite(sd) and sd >= 0):
        raise InputError(f"data.measurement_noise={sd}: expected a standard deviation >= 0 (0: noise-free)")
    if sd > 0 and measured_path is None:
        raise InputError(
            f"data.measurement_noise={sd} applies to measurements read from a file (data.measured_path); generated "
            "measurements are noise-free: to try noisy ones, write them to a file (scripts/export_measured.py --noise SD)"
        )
