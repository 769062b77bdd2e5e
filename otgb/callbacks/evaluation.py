"""The evaluation as a Lightning callback: metrics at validation and test, baselines, reports."""

from __future__ import annotations

import functools
import hashlib
import logging
import time
from pathlib import Path
from typing import Any

import torch
from lightning import Callback, LightningModule, Trainer
from lightning.pytorch.utilities import rank_zero_info
from torch import Tensor

from otgb.data.measured import cache_key, save_atomically, with_measurement_noise
from otgb.data.seeding import derive_seed
from otgb.errors import InputError
from otgb.metrics.c2st import CLASSIFIERS
from otgb.metrics.classifiers import PRECISIONS, native_bf16
from otgb.metrics.joint import JointEvaluator, reference_scores, split_half_scores
from otgb.metrics.mmdagg import PAPER_EXPONENTS, check_options
from otgb.reports import write_report

EVERY_VALIDATION = ("mmd", "mmd2_median", "energy")
POINTWISE = ("abs_err", "nrmse")
TESTS = ("mmdagg_reject", "mmdagg_pvalue", "mmdagg_mmd2", "c2st")
log = logging.getLogger("otgb.evaluation")  # a warning prints as its one line, like the solvers'


class Evaluation(Callback):
    """Scores the map's draws on the validation/test sets, in the data module's mode.

    Joint mode (a known DGP, :class:`otgb.data.SimulationDataModule`): rows (theta, x0, y) of
    the map's draws against the DGP's draws for the same inputs (:mod:`otgb.metrics.joint`).
    Marginal mode (measurements from a file): the map's draws for inputs from the priors against
    the held-out measurements, trajectories alone; when the file recorded inputs (theta and/or
    x0), the map is run on exactly those and the same metrics on rows (recorded inputs, y) are
    added as ``joint_<name>`` (with ABS ERR and N-RMSE when both theta and x0 are recorded).

    - Every validation: MMD, the energy distance and, where pairs exist, ABS ERR and N-RMSE,
      as ``val/<name>``.
    - Every ``tests_every``-th validation and always at test: also the MMDAgg test and C2ST.
    - Once per run and stage (the first validation, and the test): the same metrics for f_p
      alone (``<stage>/fp_<name>``: f_p simulations of the same inputs as the map's) and the
      Reference (``<stage>/ref_<name>`` and ``ref_<name>_std`` over ``reference_repeats``
      random splits: DGP draws against independent DGP draws on the same inputs when joint,
      one half of the held-out measurements against the other when marginal).
    - At test, ``metrics.json`` and ``metrics.md`` (model, f_p alone, Reference, and the mode)
      are written to the run's log directory (see :func:`otgb.reports.write_report`), with
      the energy distance per time step and observed component.

    The model's validation/test steps return ``{"y_hat": (B, M, T, *obs)}``; the metrics
    accumulate over batches and sync across processes.

    Args:
        tests_every: Run MMDAgg and C2ST at every n-th validation (0: only at test).
        c2st_folds: Cross-validation folds of the C2ST.
        c2st_classifier: C2ST classifier: "auto" (an MLP up to 200 features, else a conv net), "mlp", "conv"
            or "paper" (the paper's weak judge network).
        c2st_precision: C2ST arithmetic: "auto" (bfloat16 where the hardware multiplies it natively), "32-true" or "bf16-mixed".
        mmdagg_permutations: Permutations for each of MMDAgg's two stages.
        reference_repeats: Random splits averaged for the Reference.
        seed: Seed of the evaluation's own randomness (folds, permutations, splits).
        cache_baselines: Keep the f_p-alone and Reference scores of a set in the data module's ``cache_dir``, so
            that a later run on the same set with the same settings reads them instead of scoring them again
            (they do not depend on the map; every part of them is seeded, so a read score equals a recomputed one).
            The cache is keyed by the set's content, these settings, the device and the scoring code.
    """

    def __init__(
        self,
        tests_every: int = 5,
        c2st_folds: int = 5,
        c2st_classifier: str = "auto",
        c2st_precision: str = "auto",
        mmdagg_permutations: int = 500,
        reference_repeats: int = 5,
        seed: int = 0,
        cache_baselines: bool = True,
    ) -> None:
        if tests_every < 0 or reference_repeats < 1 or c2st_folds < 2:
            raise InputError(
                "evaluation: need tests_every >= 0, reference_repeats >= 1, c2st_folds >= 2; got "
                f"tests_every={tests_every}, reference_repeats={reference_repeats}, c2st_folds={c2st_folds}"
            )
        if c2st_classifier not in CLASSIFIERS or c2st_precision not in PRECISIONS:
            raise InputError(
                f"evaluation: c2st_classifier={c2st_classifier!r}, c2st_precision={c2st_precision!r}; "
                f"expected one of {CLASSIFIERS} and one of {PRECISIONS}"
            )
        try:
            check_options(0.05, PAPER_EXPONENTS, mmdagg_permutations, mmdagg_permutations)
        except ValueError as error:
            raise InputError(f"evaluation.mmdagg_permutations: {error}") from None
        self.tests_every, self.reference_repeats, self.seed = tests_every, reference_repeats, seed
        self.cache_baselines, self.cache_dir = cache_baselines, None
        self.options = dict(
            c2st_folds=c2st_folds,
            c2st_classifier=c2st_classifier,
            c2st_precision=c2st_precision,
            mmdagg_permutations=mmdagg_permutations,
            seed=seed,
        )
        self.plan: dict[str, tuple[tuple[str, ...], bool, bool]] = {}
        self.evaluators: dict[str, JointEvaluator] = {}
        self.validations = 0
        self.baselines_logged = False
        self.noise = 0.0

    # --- what is compared -------------------------------------------------------------------
    def validation_metrics(self, datamodule: Any) -> list[str]:
        """The ``val/<name>`` scalars every validation logs for this data module (tests included if every time)."""
        names = list(EVERY_VALIDATION) + (list(TESTS) if self.tests_every == 1 else [])
        one_draw = datamodule.source.draws_per_input == 1
        metrics = []
        for prefix, (inputs, paired, _) in datamodule.source.evaluation_plan().items():
            pointwise = one_draw and JointEvaluator.is_pointwise(inputs, paired)
            metrics += [f"val/{prefix}{name}" for name in (list(POINTWISE) if pointwise else []) + names]
        return metrics

    def setup(self, trainer: Trainer, pl_module: LightningModule, stage: str) -> None:
        datamodule = trainer.datamodule
        self._check_monitors(trainer, datamodule)
        shape = tuple(pl_module.physics.trajectory_shape)
        self.plan = datamodule.source.evaluation_plan()
        self.noise = datamodule.source.measurement_noise  # put on the map's and f_p's draws, as on the measurements

        def make(prefix: str, paired: bool, sync: bool, across: bool) -> JointEvaluator:
            per_time = prefix == ""  # the per-time statistic reads the trajectories alone: once per set
            inputs = self.plan[prefix][0]
            halves = self.reference_repeats if across else 0  # the Reference's splits
            return JointEvaluator(
                shape, inputs=inputs, paired=paired, per_time=per_time, device=pl_module.device, sync=sync,
                across_halves=halves, **self.options,
            )  # fmt: skip

        self.evaluators = {prefix: make(prefix, paired, True, across) for prefix, (_, paired, across) in self.plan.items()}
        # f_p and the Reference are scored on the whole set on every rank: no cross-process sync
        self.baselines = {prefix: make(prefix, paired, False, across) for prefix, (_, paired, across) in self.plan.items()}
        self.reference_on_same_inputs = datamodule.source.reference_on_same_inputs
        self.cache_dir = getattr(datamodule, "cache_dir", None) if self.cache_baselines else None
        if not self.reference_on_same_inputs:  # halves of the measurements have different inputs: unpaired
            self.references = {prefix: make(prefix, False, False, False) for prefix in self.plan}

    def _check_monitors(self, trainer: Trainer, datamodule: Any) -> None:
        """A checkpoint must monitor a metric that every validation of this mode logs."""
        available = self.validation_metrics(datamodule)
        for checkpoint in trainer.checkpoint_callbacks:
            monitor = getattr(checkpoint, "monitor", None)
            if monitor is None or monitor in available:
                continue
            if monitor.removeprefix("val/").removeprefix("joint_") in TESTS and self.tests_every != 1:
                raise InputError(
                    f"ModelCheckpoint(monitor={monitor!r}) needs that metric at every validation, but "
                    f"evaluation.tests_every={self.tests_every} computes it only every {self.tests_every} validations "
                    "(0: only at test): set evaluation.tests_every=1 or monitor val/mmd"
                )
            raise InputError(
                f"ModelCheckpoint(monitor={monitor!r}): the {datamodule.mode} evaluation does not log it; "
                f"choose one of {available}"
            )

    # --- accumulate -----------------------------------------------------------------------
    def on_validation_batch_end(self, trainer, pl_module, outputs, batch, batch_idx, dataloader_idx=0) -> None:
        if not trainer.sanity_checking:
            self._update(outputs, batch, pl_module, ("val", batch_idx))

    def on_test_batch_end(self, trainer, pl_module, outputs, batch, batch_idx, dataloader_idx=0) -> None:
        self._update(outputs, batch, pl_module, ("test", batch_idx))

    def _update(self, outputs: Any, batch: dict[str, Tensor], pl_module: LightningModule, key: tuple) -> None:
        if not isinstance(outputs, dict) or "y_hat" not in outputs:
            raise TypeError("Evaluation: the model's validation/test step must return {'y_hat': (B, M, T, *obs)}")
        if next(iter(self.evaluators.values())).device != pl_module.device:  # the module moved after setup
            self.setup(pl_module.trainer, pl_module, "")
        y_hat = outputs["y_hat"]
        as_measured = self._as_measured(y_hat, *key, pl_module.global_rank)
        for evaluator in self.evaluators.values():
            evaluator.update(y_hat, batch, as_measured=as_measured)

    def _as_measured(self, draws: Tensor, *key: object) -> Tensor:
        """Draws with the measurements' noise (``data.measurement_noise``), the same on every run for a batch: what
        the two-sample metrics compare with the measurements (the pointwise errors take the draws themselves)."""
        if self.noise == 0:
            return draws
        generator = torch.Generator(device=draws.device).manual_seed(derive_seed(self.seed, "measurement noise", *key))
        return with_measurement_noise(draws, self.noise, generator)

    # --- compute and log ------------------------------------------------------------------
    def on_validation_epoch_end(self, trainer: Trainer, pl_module: LightningModule) -> None:
        if trainer.sanity_checking or next(iter(self.evaluators.values())).one_to_one is None:
            return
        self.validations += 1
        tests = self.tests_every > 0 and self.validations % self.tests_every == 0
        results = self._model_results(tests)
        if not self.baselines_logged:
            results.update(self._baselines(trainer.datamodule.val_set))
            self.baselines_logged = True
        self._log(pl_module, "val", results)

    def on_test_start(self, trainer: Trainer, pl_module: LightningModule) -> None:
        if pl_module.scored_untrained(trainer):  # after Lightning restored any checkpoint
            rank_zero_info(
                "otgb test: no checkpoint: scoring the map as initialised, untrained "
                "(give --ckpt_path=<run>/checkpoints/best-step=*.ckpt or last.ckpt)"
            )

    def on_test_epoch_end(self, trainer: Trainer, pl_module: LightningModule) -> None:
        datamodule = trainer.datamodule
        results = self._model_results(tests=True)
        results.update(self._baselines(datamodule.test_set))
        scalars = self._log(pl_module, "test", results)
        log_dir = trainer.log_dir  # a collective call under DDP: every process makes it
        if trainer.is_global_zero and log_dir is not None:
            data = datamodule.test_set
            run = {
                "log_dir": str(log_dir),
                "name": Path(log_dir).parent.name,
                "ckpt_path": str(trainer.ckpt_path) if trainer.ckpt_path else pl_module.loaded_from,
                "global_step": trainer.global_step if pl_module.restored_step is None else pl_module.restored_step,
                "seed": torch.initial_seed(),
                **self.mode_facts(datamodule),
                "n_inputs": len(data["y"]),
                "draws_per_input": data["y"].shape[1],
                "sample_sizes": datamodule.source.sample_sizes(len(data["y"]), data["y"].shape[1]),
                "untrained": pl_module.scored_untrained(trainer),
            }
            per_time = {name: value for name, value in results.items() if value.dim() > 0}
            write_report(Path(log_dir), run, scalars, per_time, self._labels(pl_module))

    @staticmethod
    def mode_facts(datamodule: Any) -> dict[str, Any]:
        """What produced the numbers: the mode, the measured file and its split when marginal, and the measurements the
        checkpoint was trained on where they are others."""
        trained_on = getattr(datamodule, "trained_on", None)
        return datamodule.source.facts() | ({"trained_on": trained_on} if trained_on else {})

    @staticmethod
    def _labels(pl_module: LightningModule) -> dict[str, list]:
        physics = pl_module.physics
        return {"times": physics.observation_times().tolist(), "components": list(physics.observed)}

    def _model_results(self, tests: bool) -> dict[str, Tensor]:
        start = time.perf_counter()
        results = {}
        for prefix, evaluator in self.evaluators.items():
            results.update({prefix + k: v for k, v in evaluator.compute(tests).items()})
            evaluator.reset()
        results["eval_seconds"] = torch.tensor(time.perf_counter() - start)
        return results

    def _baselines(self, data: dict[str, Tensor]) -> dict[str, Tensor]:
        """f_p alone and the Reference on a whole set, all metrics: ``fp_<name>``, ``ref_<name>``; read from the
        cache when an earlier run scored the same set with the same settings (``cache_baselines``)."""
        if self.cache_dir is None:
            return self._score_baselines(data)
        device = next(iter(self.baselines.values())).device
        hardware = torch.cuda.get_device_name(device) if device.type == "cuda" else f"cpu bf16={native_bf16(device)}"
        settings = (self.options, self.plan, self.reference_repeats, self.reference_on_same_inputs, self.noise, hardware)
        key = cache_key(settings, torch.__version__, _scoring_code(), _content(data))
        path, started = Path(self.cache_dir) / f"baselines-{key}.pt", time.perf_counter()
        if path.is_file():
            rank_zero_info(f"otgb: f_p alone and the Reference on this set: read from {path}")
            results = torch.load(path, map_location="cpu", weights_only=True)
            return results | {"fp_eval_seconds": torch.tensor(time.perf_counter() - started), "ref_eval_seconds": torch.zeros(())}
        rank_zero_info(f"otgb: scoring f_p alone and the Reference on this set (once: kept in {path.parent} for later runs)")
        results = self._score_baselines(data)
        try:
            save_atomically(results, path)
        except OSError as error:  # a read-only folder costs the next run the scoring, not this run its results
            log.warning(f"otgb: evaluation.cache_baselines: cannot write {path} ({error.strerror}); scored again next run")
        return results

    def _score_baselines(self, data: dict[str, Tensor]) -> dict[str, Tensor]:
        results = {}
        start = time.perf_counter()
        fp_draws = data["x"].unsqueeze(1).expand_as(data["y"])
        as_measured = self._as_measured(fp_draws, "f_p")
        for prefix, evaluator in self.baselines.items():
            scores = evaluator.evaluate(fp_draws, data, tests=True, as_measured=as_measured)
            results.update({f"fp_{prefix}{k}": v for k, v in scores.items()})
        results["fp_eval_seconds"] = torch.tensor(time.perf_counter() - start)
        start = time.perf_counter()
        for prefix in self.plan:
            if self.reference_on_same_inputs:
                reference = reference_scores(self.baselines[prefix], data, True, self.reference_repeats, self.seed)
            else:
                reference = split_half_scores(self.references[prefix], data, True, self.reference_repeats, self.seed)
            results.update({f"ref_{prefix}{k}": v for k, v in reference.items()})
        results["ref_eval_seconds"] = torch.tensor(time.perf_counter() - start)
        return {name: value.cpu() for name, value in results.items()}

    def _log(self, pl_module: LightningModule, stage: str, results: dict[str, Tensor]) -> dict[str, Tensor]:
        """Log the scalar results as ``<stage>/<name>`` and return them (vectors stay out of the loggers).

        The metrics' states are synced across processes before they are computed, so every
        process holds the same values; ``sync_dist`` averages them all the same (timings differ).
        """
        scalars = {k: v.float() for k, v in results.items() if v.dim() == 0}
        pl_module.log_dict({f"{stage}/{k}": v for k, v in scalars.items()}, sync_dist=True)
        return scalars


def _content(data: dict[str, Tensor]) -> str:
    """A digest of a set's tensors (names, shapes, types and values)."""
    digest = hashlib.sha256()
    for name in sorted(data):
        tensor = data[name].detach().cpu().contiguous()
        digest.update(f"{name}{tuple(tensor.shape)}{tensor.dtype}".encode())
        digest.update(tensor.reshape(-1).view(torch.uint8).numpy().tobytes())
    return digest.hexdigest()


@functools.cache
def _scoring_code() -> str:
    """A digest of the code that scores the baselines (this module and otgb.metrics): a cached score is never one of
    other code."""
    files = [Path(__file__), *sorted(Path(__file__).parents[1].joinpath("metrics").glob("*.py"))]
    return hashlib.sha256(b"".join(path.read_bytes() for path in files)).hexdigest()
