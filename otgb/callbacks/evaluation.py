"""The joint evaluation as a Lightning callback: metrics at validation and test, baselines, reports."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import torch
from lightning import Callback, LightningModule, Trainer
from torch import Tensor

from otgb.metrics.c2st import CLASSIFIERS
from otgb.metrics.classifiers import PRECISIONS
from otgb.metrics.joint import JointEvaluator, reference_scores
from otgb.metrics.mmdagg import PAPER_EXPONENTS, check_options
from otgb.reports import write_report


class JointEvaluation(Callback):
    """Scores the map's draws on the joint validation/test sets (:mod:`otgb.metrics.joint`).

    - Every validation: ABS ERR and N-RMSE (one-to-one sets) and MMD, as ``val/<name>``.
    - Every ``tests_every``-th validation and always at test: also the MMDAgg test and C2ST.
    - Once per run and stage (the first validation, and the test): the same metrics for
      f_p alone (``<stage>/fp_<name>``: the uncorrected simulation as the prediction) and the
      Reference (``<stage>/ref_<name>`` and ``ref_<name>_std``: DGP draws against independent
      DGP draws on the same inputs, over ``reference_repeats`` random splits).
    - At test, ``metrics.json`` and ``metrics.md`` (model, f_p alone, Reference) are written
      to the run's log directory (see :func:`otgb.reports.write_report`).

    The model's validation/test steps return ``{"y_hat": (B, M, T, *obs)}``; the metrics
    accumulate over batches and sync across processes.

    Args:
        tests_every: run MMDAgg and C2ST at every n-th validation (0: only at test).
        c2st_folds, c2st_classifier: C2ST settings ("auto", "mlp" or "conv").
        c2st_precision: the C2ST classifier's arithmetic: "auto" (bfloat16 mixed precision where
            the hardware multiplies bfloat16 natively, else float32), "32-true" or "bf16-mixed".
        mmdagg_permutations: permutations for each of MMDAgg's two stages.
        reference_repeats: random splits for the Reference.
        seed: seed of the evaluation's own randomness (folds, permutations, splits).
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
    ) -> None:
        if tests_every < 0 or reference_repeats < 1 or c2st_folds < 2:
            raise ValueError(
                "evaluation: need tests_every >= 0, reference_repeats >= 1, c2st_folds >= 2; got "
                f"tests_every={tests_every}, reference_repeats={reference_repeats}, c2st_folds={c2st_folds}"
            )
        if c2st_classifier not in CLASSIFIERS or c2st_precision not in PRECISIONS:
            raise ValueError(
                f"evaluation: c2st_classifier={c2st_classifier!r}, c2st_precision={c2st_precision!r}; "
                f"expected one of {CLASSIFIERS} and one of {PRECISIONS}"
            )
        check_options(0.05, PAPER_EXPONENTS, mmdagg_permutations, mmdagg_permutations)
        self.tests_every, self.reference_repeats, self.seed = tests_every, reference_repeats, seed
        self.options = dict(
            c2st_folds=c2st_folds,
            c2st_classifier=c2st_classifier,
            c2st_precision=c2st_precision,
            mmdagg_permutations=mmdagg_permutations,
            seed=seed,
        )
        self.evaluator: JointEvaluator | None = None
        self.baseline_evaluator: JointEvaluator | None = None
        self.validations = 0
        self.baselines_logged = False

    def setup(self, trainer: Trainer, pl_module: LightningModule, stage: str) -> None:
        self._check_monitors(trainer)
        shape = tuple(pl_module.physics.trajectory_shape)
        self.evaluator = JointEvaluator(shape, device=pl_module.device, **self.options)
        # f_p and the Reference are scored on the whole set on every rank: no cross-process sync
        self.baseline_evaluator = JointEvaluator(shape, device=pl_module.device, sync=False, **self.options)

    def _check_monitors(self, trainer: Trainer) -> None:
        """A checkpoint monitoring a test metric needs that metric at every validation."""
        for checkpoint in trainer.checkpoint_callbacks:
            monitor = getattr(checkpoint, "monitor", None) or ""
            if monitor.startswith(("val/c2st", "val/mmdagg")) and self.tests_every != 1:
                raise ValueError(
                    f"ModelCheckpoint(monitor={monitor!r}) needs that metric at every validation, but "
                    f"evaluation.tests_every={self.tests_every} computes it only every {self.tests_every} validations "
                    "(0: only at test): set evaluation.tests_every=1 or monitor val/mmd"
                )

    # --- accumulate -----------------------------------------------------------------------
    def on_validation_batch_end(self, trainer, pl_module, outputs, batch, batch_idx, dataloader_idx=0) -> None:
        if not trainer.sanity_checking:
            self._update(outputs, batch, pl_module)

    def on_test_batch_end(self, trainer, pl_module, outputs, batch, batch_idx, dataloader_idx=0) -> None:
        self._update(outputs, batch, pl_module)

    def _update(self, outputs: Any, batch: dict[str, Tensor], pl_module: LightningModule) -> None:
        if not isinstance(outputs, dict) or "y_hat" not in outputs:
            raise TypeError("JointEvaluation: the model's validation/test step must return {'y_hat': (B, M, T, *obs)}")
        if self.evaluator.device != pl_module.device:  # the module moved to its device after setup
            self.setup(pl_module.trainer, pl_module, "")
        self.evaluator.update(outputs["y_hat"], batch["y"], batch["theta"], batch["x0"])

    # --- compute and log ------------------------------------------------------------------
    def on_validation_epoch_end(self, trainer: Trainer, pl_module: LightningModule) -> None:
        if trainer.sanity_checking or self.evaluator.one_to_one is None:
            return
        self.validations += 1
        tests = self.tests_every > 0 and self.validations % self.tests_every == 0
        results = self._model_results(tests)
        if not self.baselines_logged:
            results.update(self._baselines(trainer.datamodule.val_set))
            self.baselines_logged = True
        self._log(pl_module, "val", results)

    def on_test_epoch_end(self, trainer: Trainer, pl_module: LightningModule) -> None:
        results = self._model_results(tests=True)
        results.update(self._baselines(trainer.datamodule.test_set))
        self._log(pl_module, "test", results)
        if trainer.is_global_zero and trainer.log_dir is not None:
            data = trainer.datamodule.test_set
            run = {
                "log_dir": str(trainer.log_dir),
                "name": Path(trainer.log_dir).parent.name,
                "ckpt_path": str(trainer.ckpt_path) if trainer.ckpt_path else None,
                "global_step": trainer.global_step if pl_module.restored_step is None else pl_module.restored_step,
                "seed": torch.initial_seed(),
                "n_inputs": len(data["y"]),
                "draws_per_input": data["y"].shape[1],
            }
            write_report(Path(trainer.log_dir), run, results)

    def _model_results(self, tests: bool) -> dict[str, Any]:
        start = time.perf_counter()
        results = self.evaluator.compute(tests)
        self.evaluator.reset()
        results["eval_seconds"] = torch.tensor(time.perf_counter() - start)
        return results

    def _baselines(self, data: dict[str, Tensor]) -> dict[str, Tensor]:
        """f_p alone and the Reference on a whole joint set, all metrics: ``fp_<name>``, ``ref_<name>``."""
        results = {}
        start = time.perf_counter()
        fp_draws = data["x"].unsqueeze(1).expand_as(data["y"])
        results.update({f"fp_{k}": v for k, v in self.baseline_evaluator.evaluate(fp_draws, data, tests=True).items()})
        results["fp_eval_seconds"] = torch.tensor(time.perf_counter() - start)
        start = time.perf_counter()
        reference = reference_scores(self.baseline_evaluator, data, True, self.reference_repeats, self.seed)
        results.update({f"ref_{k}": v for k, v in reference.items()})
        results["ref_eval_seconds"] = torch.tensor(time.perf_counter() - start)
        return results

    def _log(self, pl_module: LightningModule, stage: str, results: dict[str, Tensor]) -> None:
        pl_module.log_dict({f"{stage}/{k}": v.float() for k, v in results.items()})
