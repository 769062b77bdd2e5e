"""A map T_phi trained against a critic f_psi as in Algorithm 1 (paper eq. kernel-maximin).

One training step is one iteration of Algorithm 1:

    for i in 1..T_max:                       # map updates, a fresh source batch each
        x = S_fp(x0, theta);  z ~ eta (|Z| draws per x)
        L_T = objective(x, T_x(Z), f)        # kernel weak OT: mean_x [ C_hat_{k,gamma}(x, T_x(Z)) - mean_z f(T_x(z)) ]
        phi <- phi - grad L_T
    for j in 1..critic_steps:                # critic updates (1 in Algorithm 1; 5 in the WGAN-GP baseline)
        y ~ nu;  y_hat = T(x) (the last map update's outputs, then a fresh source batch each)
        L_f = mean f(y_hat) - mean f(y) + lambda * GP
        psi <- psi - grad L_f

The objective is a component (``model.objective``): :class:`otgb.ot.WeakTransport` (otgb's
method) or :class:`otgb.ot.WassersteinGAN` (the baseline). Optimisation is manual.
``trainer.global_step`` counts iterations of Algorithm 1: the map updates, and the critic
updates but the last, go through the strategy's precision plugin without touching Lightning's
step counter, so ``max_steps``, ``val_check_interval`` and ``log_every_n_steps`` all count
iterations. Map updates are logged as ``train/map_updates``.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch
from lightning import LightningModule, Trainer
from lightning.pytorch.cli import LRSchedulerCallable, OptimizerCallable
from torch import Tensor, nn
from torch.optim.swa_utils import AveragedModel, get_ema_multi_avg_fn

from otgb.compiling import new_training_step
from otgb.data.gaps import comparable, has_gaps
from otgb.data.measured import with_measurement_noise
from otgb.data.seeding import derive_seed
from otgb.errors import InputError
from otgb.guard import TrainingDiverged, UpdateGuard, diagnosis
from otgb.ot import Objective, WeakTransport, critic_loss
from otgb.parallel import SigtermAgreement, average_gradients, without_gradient_sync
from otgb.physics.base import PhysicsModel, SimulationDiverged
from otgb.physics.solvers import plan_solves
from otgb.schedules import BatchScaledRate

MapFactory = Callable[[PhysicsModel, int], nn.Module]
CriticFactory = Callable[[tuple], nn.Module]
LATENTS = ("normal", "uniform", "categorical")


def _adam(params: Any) -> torch.optim.Optimizer:
    return torch.optim.Adam(params, lr=1e-4)


class MapTraining(LightningModule):
    """Learns T_phi(x; theta, z) against a critic f_psi by an objective (kernel weak OT by default).

    Args:
        physics: f_p (linked from the data module by the CLI).
        transport_map: builds the map from (physics, z_dim), e.g. :class:`otgb.models.GreyBoxODE`.
        critic: builds the critic from the trajectory shape (T, *obs).
        z_dim: size of the latent z; 0 for a deterministic map.
        latent: distribution eta of z: "normal" (N(0, I)), "uniform" (U(-1, 1)) or "categorical"
            (one of the z_dim one-hot vectors, equally likely: a discrete latent for a missing
            effect with a few regimes, as the paper uses for some one-to-many tasks).
        n_z: |Z|, latent draws per source sample in the cost.
        objective: what the map minimises (:mod:`otgb.ot.objectives`; default: kernel weak OT
            with gamma 0 and the distance kernel).
        t_max: map updates per training step.
        critic_steps: critic updates per training step (each on a fresh measured batch; all but
            the first on a fresh source batch).
        gp_weight: lambda, weight of the gradient penalty.
        gp_one_sided: penalise only critic gradient norms above 1 (:func:`otgb.ot.gradient_penalty`);
            False: the two-sided penalty of the paper's Algorithm 1.
        grad_clip: max gradient norm for both networks (None: no clipping).
        ema_decay: if set, validation, test and figures use an exponential moving average
            of the map's weights with this decay per map update (None: the map itself).
        map_optimizer: optimiser factory of the map T_phi (default: Adam).
        critic_optimizer: optimiser factory of the critic f_psi (default: Adam).
        map_scheduler: learning-rate schedule factory of the map's optimiser, stepped once
            per training step (None: a constant learning rate).
        critic_scheduler: learning-rate schedule factory of the critic's optimiser, stepped
            once per training step (None: a constant learning rate).
        lr_batch_rule: scales both optimisers' learning rates to the data's batch size before training
            (:class:`otgb.schedules.BatchScaledRate`; None: the rates as configured).
        max_consecutive_skips: An update whose loss or gradients are NaN/Inf (a solve that blew
            up) is skipped and counted (``train/skipped_steps``); this many in a row stop the run
            with a message naming what diverged, after saving the last good state as last.ckpt.
    """

    def __init__(
        self,
        physics: PhysicsModel,
        transport_map: MapFactory,
        critic: CriticFactory,
        z_dim: int = 0,
        latent: str = "normal",
        n_z: int = 1,
        objective: Objective | None = None,
        t_max: int = 5,
        critic_steps: int = 1,
        gp_weight: float = 1.0,
        gp_one_sided: bool = False,
        grad_clip: float | None = None,
        ema_decay: float | None = None,
        map_optimizer: OptimizerCallable = _adam,
        critic_optimizer: OptimizerCallable = _adam,
        map_scheduler: LRSchedulerCallable | None = None,
        critic_scheduler: LRSchedulerCallable | None = None,
        lr_batch_rule: BatchScaledRate | None = None,
        max_consecutive_skips: int = 10,
    ) -> None:
        super().__init__()
        self._check_settings(z_dim, latent, n_z, t_max, critic_steps, gp_weight, grad_clip)
        self.objective = WeakTransport() if objective is None else objective
        self.objective.check_draws(n_z)
        self.save_hyperparameters(
            ignore=[
                "objective",
                "physics",
                "transport_map",
                "critic",
                "map_optimizer",
                "critic_optimizer",
                "map_scheduler",
                "critic_scheduler",
                "lr_batch_rule",
            ]
        )
        self.automatic_optimization = False
        self.physics = physics
        self.transport_map = transport_map(physics, z_dim)
        self.critic = critic(tuple(physics.trajectory_shape))
        if ema_decay is not None and not 0.0 < ema_decay < 1.0:
            raise InputError(f"model.ema_decay={ema_decay}: expected a value in (0, 1) or None")
        self.map_average = (
            AveragedModel(self.transport_map, multi_avg_fn=get_ema_multi_avg_fn(ema_decay)) if ema_decay is not None else None
        )
        self.z_dim, self.latent, self.n_z = z_dim, latent, n_z
        self.t_max, self.critic_steps, self.gp_weight, self.grad_clip = t_max, critic_steps, gp_weight, grad_clip
        self.gp_one_sided = gp_one_sided
        if max_consecutive_skips < 1:
            raise InputError(f"model.max_consecutive_skips={max_consecutive_skips}: expected >= 1")
        self.guard = UpdateGuard(max_consecutive_skips)
        self.sigterm = SigtermAgreement()
        self.optimizer_factories = (map_optimizer, critic_optimizer)
        self.scheduler_factories = (map_scheduler, critic_scheduler)
        self.lr_batch_rule = lr_batch_rule
        self.map_updates = 0
        self.elapsed_before = 0.0
        self.restored_step: int | None = None  # global step of the checkpoint this module was loaded from
        self.loaded_from: str | None = None  # the checkpoint otgb.runs.load_weights loaded, outside a Trainer's restore
        self._fit_clock: float | None = None
        self._steps: float = math.inf  # the fit's training steps, known when training starts
        self._generator: torch.Generator | None = None
        self.draw_seed: int | None = None  # key of the module's draws in a Trainer; the run's seed, kept in checkpoints

    @staticmethod
    def _check_settings(
        z_dim: int, latent: str, n_z: int, t_max: int, critic_steps: int, gp_weight: float, grad_clip: float | None
    ) -> None:
        if z_dim < 0 or n_z < 1 or t_max < 1 or critic_steps < 1:
            raise InputError(
                "model: need z_dim >= 0, n_z >= 1, t_max >= 1, critic_steps >= 1; "
                f"got z_dim={z_dim}, n_z={n_z}, t_max={t_max}, critic_steps={critic_steps}"
            )
        if latent not in LATENTS:
            raise InputError(f"model.latent={latent!r}: expected one of {LATENTS}")
        if latent == "categorical" and z_dim < 2:
            raise InputError(f"model.latent='categorical' draws one of z_dim categories: needs z_dim >= 2, got {z_dim}")
        if n_z > 1 and z_dim == 0:
            raise InputError(f"model.n_z={n_z} draws of a deterministic map (z_dim=0) are all equal: set z_dim > 0 or n_z = 1")
        if gp_weight < 0 or (grad_clip is not None and grad_clip <= 0):
            raise InputError(f"model: need gp_weight >= 0 and grad_clip > 0 or None; got {gp_weight}, {grad_clip}")

    # --- the map ------------------------------------------------------------------------
    @property
    def generator(self) -> torch.Generator:
        """The module's own RNG (latent z, penalty points), on its device.

        In a Trainer it is keyed afresh at every training step and evaluation epoch by (seed,
        stage, process rank, global step) (:meth:`_key_draws`): each process draws its own z, a
        resumed run repeats no draw and needs no RNG state, and how often validation runs does
        not change training's draws. Outside a Trainer it is seeded by the global seed.
        """
        if self._generator is None or self._generator.device != self.device:
            self._generator = torch.Generator(device=self.device).manual_seed(torch.initial_seed())
        return self._generator

    def _key_draws(self, stage: str) -> None:
        key = derive_seed(self.draw_seed, stage, self.global_rank, self.trainer.global_step)
        self._generator = torch.Generator(device=self.device).manual_seed(key)

    def sample_z(self, n: int) -> Tensor:
        shape = (n, self.z_dim)
        if self.latent == "uniform":
            return 2 * torch.rand(shape, device=self.device, generator=self.generator) - 1
        if self.latent == "categorical":
            category = torch.randint(self.z_dim, (n,), device=self.device, generator=self.generator)
            return torch.nn.functional.one_hot(category, self.z_dim).to(torch.get_default_dtype())
        return torch.randn(shape, device=self.device, generator=self.generator)

    @property
    def map_has_weights(self) -> bool:
        """Whether the map has weights to train (not f_p alone, nor a complete physics)."""
        return any(True for _ in self.transport_map.parameters())

    def scored_untrained(self, trainer: Trainer) -> bool:
        """Whether ``trainer`` scores the map as initialised: it has weights, and no checkpoint (given to the Trainer
        or loaded by :func:`otgb.runs.load_weights`) and no training in this Trainer set them."""
        loaded = trainer.ckpt_path is not None or self.restored_step is not None or self.loaded_from is not None
        return self.map_has_weights and not loaded and trainer.global_step == 0

    def evaluation_map(self) -> nn.Module:
        """The map that evaluation uses: the moving average of its weights when there is one, else the map itself."""
        return self.map_average.module if self.map_average is not None else self.transport_map

    def generate(
        self, x: Tensor, x0: Tensor, theta: Tensor, n_draws: int, averaged: bool = True, signals: Tensor | None = None
    ) -> Tensor:
        """``n_draws`` outputs of the map per input: (B, n_draws, T, *obs); ``signals`` (B, T_u, I) are the inputs' signals
        of a driven model.

        ``averaged`` selects the moving average of the map's weights when there is one (for
        evaluation); training passes False.
        """
        batch = x.shape[0]
        rep = lambda v: None if v is None else v.repeat_interleave(n_draws, dim=0)  # noqa: E731
        transport_map = self.evaluation_map() if averaged else self.transport_map
        y_hat = transport_map(rep(x), rep(x0), rep(theta), self.sample_z(batch * n_draws), signals=rep(signals))
        return y_hat.reshape(batch, n_draws, *y_hat.shape[1:])

    # --- Algorithm 1 --------------------------------------------------------------------
    def training_step(self, batch: dict[str, Tensor], batch_idx: int) -> None:
        map_opt, critic_opt = self.optimizers()
        sources, measured = self.t_max + self.critic_steps - 1, self.critic_steps
        if batch["x0"].shape[0] != sources or batch["y"].shape[0] != measured:
            raise ValueError(
                f"a training item holds {batch['x0'].shape[0]} source and {batch['y'].shape[0]} measured batches; the model "
                f"expects t_max + critic_steps - 1 = {sources} and critic_steps = {measured}"
            )
        self._key_draws("train")
        self.toggle_optimizer(map_opt)
        y_hat, parts = None, {}
        for k in range(self.t_max):
            y_hat_k, parts_k = self._map_update(map_opt, _inputs(batch, k), batch["y"][0])
            if y_hat_k is not None:
                y_hat, parts = y_hat_k, parts_k
        self.untoggle_optimizer(map_opt)

        self.toggle_optimizer(critic_opt)
        for j in range(self.critic_steps):
            if j > 0:  # a fresh source batch for each further critic update
                k = self.t_max + j - 1
                with torch.no_grad():
                    y_hat = self._generate_or_none(_inputs(batch, k))
            critic_parts = self._critic_update(critic_opt, batch["y"][j], y_hat, last=j == self.critic_steps - 1)
        self.untoggle_optimizer(critic_opt)

        for scheduler in self._schedulers():
            scheduler.step()
        self._log_step({**parts, **critic_parts})

    def _critic_update(self, opt: Any, y: Tensor, y_hat: Tensor | None, last: bool) -> dict[str, Tensor]:
        """One critic update on measured ``y`` and map outputs ``y_hat`` (None: the map diverged, skip).

        The last update of a step goes through the LightningOptimizer (it counts the step); the
        others, like the map's, through the strategy alone.
        """
        if y_hat is None:  # no map output to train the critic on: the map is what diverged
            critic_parts, blame = {}, ("map", "every map update of the step gave NaN/Inf")
        else:
            y_hat, y = self._as_measured(y_hat.detach().flatten(0, 1), y)
            loss, critic_parts = critic_loss(self.critic, y, y_hat, self.gp_weight, self.generator, self.gp_one_sided)
            critic_parts["critic_loss"], blame = loss, ("critic", "loss or gradients NaN/Inf")
        if self._guarded_backward(opt, self.critic, blame[0], critic_parts.get("critic_loss"), blame[1]):
            self._clip(opt)
        if last:
            opt.step()  # counts the iteration; after a skip there are no gradients and nothing changes
        else:
            self.trainer.strategy.optimizer_step(opt.optimizer, closure=lambda: None, model=self)
        return critic_parts

    @property
    def _measurement_noise(self) -> float:
        return getattr(self.trainer.datamodule, "measurement_noise", 0.0)  # a Trainer fed loaders alone: none

    def _as_measured(self, y_hat: Tensor, y: Tensor) -> tuple[Tensor, Tensor]:
        """The map's outputs (B, T, *obs) and the measured batch ``y`` as the critic compares them: the outputs with the
        measurements' noise (``data.measurement_noise``), which a solve cannot produce and the map must not be pushed
        to imitate, and both with the measured batch's missing values, 0 on both sides (:mod:`otgb.data.gaps`)."""
        return comparable(with_measurement_noise(y_hat, self._measurement_noise, self.generator), y)

    def _critic_of_outputs(self, y: Tensor) -> Callable[[Tensor], Tensor]:
        """The critic as the map's loss applies it to the map's outputs: after :meth:`_as_measured` with the measured
        batch ``y``'s missing values."""
        if self._measurement_noise == 0 and not has_gaps(y):
            return self.critic
        return lambda y_hat: self.critic(self._as_measured(y_hat, y)[0])

    def _generate_or_none(self, inputs: dict[str, Tensor]) -> Tensor | None:
        try:
            return self._generate_for_training(inputs)
        except SimulationDiverged:
            return None

    def _generate_for_training(self, inputs: dict[str, Tensor]) -> Tensor:
        return self.generate(inputs["x"], inputs["x0"], inputs["theta"], self.n_z, False, inputs.get("signals"))

    def _map_update(self, opt: Any, inputs: dict[str, Tensor], y: Tensor) -> tuple[Tensor | None, dict[str, Tensor]]:
        """One map update on a source batch's ``inputs`` (x, x0, theta, signals), its critic applied as to the measured
        batch ``y`` (its missing values); (None, {}) when it was skipped (its solve or its gradients not finite)."""
        try:
            y_hat = self._generate_for_training(inputs)
        except SimulationDiverged as error:
            y_hat, loss, parts, reason = None, None, {}, str(error)
        else:
            loss, parts = self.objective.map_loss(inputs["x"], y_hat, self._critic_of_outputs(y))
            reason = "loss or gradients NaN/Inf"
        if not self._guarded_backward(opt, self.transport_map, "map", loss, reason):
            return None, {}
        self._clip(opt)
        self.trainer.strategy.optimizer_step(opt.optimizer, closure=lambda: None, model=self)
        self.map_updates += 1
        if self.map_average is not None:
            self.map_average.update_parameters(self.transport_map)
        return y_hat, parts

    def _guarded_backward(self, opt: Any, network: nn.Module, name: str, loss: Tensor | None, reason: str) -> bool:
        """Backward and average over processes; True if the loss and the gradients are finite, to step ``opt``.

        Otherwise the gradients are cleared (no step: the optimiser's state stays clean) and the
        skip is counted; a process with no finite loss contributes NaN gradients, so every process
        sees the average fail and skips alike. After ``max_consecutive_skips`` skips in a row the
        run stops (:class:`TrainingDiverged`).
        """
        opt.zero_grad(set_to_none=True)
        finite = loss is not None and bool(torch.isfinite(loss))
        if finite:
            self.manual_backward(loss)
        parameters = [p for p in network.parameters() if p.requires_grad]
        if not finite:
            for p in parameters:
                p.grad = torch.full_like(p, float("nan"))
        average_gradients(parameters, self.trainer.strategy)
        grads = [p.grad for p in parameters if p.grad is not None]
        if not grads or bool(torch.isfinite(torch.cat([g.reshape(-1) for g in grads])).all()):  # one device sync
            self.guard.passed()
            return True
        opt.zero_grad(set_to_none=True)
        if self.guard.failed(name, reason):
            self._stop_diverged()
        return False

    def _stop_diverged(self) -> None:
        """Save the current (last good) state as last.ckpt, write the logs, and stop with a message that says what to try."""
        for logger in self.trainer.loggers:
            logger.log_metrics({"train/skipped_steps": float(self.guard.skipped)}, step=self.global_step)
            logger.save()
        checkpoint = self.trainer.checkpoint_callback
        saved = None
        if checkpoint is not None and checkpoint.dirpath is not None:
            saved = str(Path(checkpoint.dirpath) / "last.ckpt")
            self.trainer.save_checkpoint(saved, weights_only=False)
        raise TrainingDiverged(self.guard.message(self._learning_rates(), saved))

    def _learning_rates(self) -> dict[str, float]:
        if self._trainer is None or not self.trainer.optimizers:
            return {}
        map_opt, critic_opt = self.trainer.optimizers
        return {"map": map_opt.param_groups[0]["lr"], "critic": critic_opt.param_groups[0]["lr"]}

    def _log_step(self, values: dict[str, Tensor]) -> None:
        """The step's figures, handed to Lightning only at the steps its loggers write (``log_every_n_steps``).

        Lightning keeps the last value of a per-step figure and writes it every ``log_every_n_steps``
        steps; each ``self.log`` call costs about half a millisecond of its bookkeeping, a tenth of a
        compiled pendulum step (``scripts/profile_step.py``), so the steps in between pass nothing.
        """
        if not self._logs_this_step():
            return
        self.log_dict({f"train/{k}": v for k, v in values.items()}, prog_bar=False)
        if "critic_gap" in values:
            self.log("train/wasserstein", values["critic_gap"], prog_bar=True)
        self.log("train/skipped_steps", float(self.guard.skipped))
        self.log("train/map_updates", float(self.map_updates))
        self.log("train/simulations", float(self.trainer.datamodule.simulations) if self.trainer.datamodule else 0.0)

    def _logs_this_step(self) -> bool:
        """Lightning's own rule for the steps its loggers write (its ``update_train_step_metrics``)."""
        return self.trainer._logger_connector.should_update_logs or bool(self.trainer.fast_dev_run)

    def _clip(self, opt: Any) -> None:
        if self.grad_clip is not None:
            self.clip_gradients(opt, gradient_clip_val=self.grad_clip, gradient_clip_algorithm="norm")

    def _schedulers(self) -> list[Any]:
        schedulers = self.lr_schedulers()
        if schedulers is None:
            return []
        return schedulers if isinstance(schedulers, list) else [schedulers]

    def configure_optimizers(self) -> Any:
        map_factory, critic_factory = self.optimizer_factories
        optimizers = [map_factory(self.transport_map.parameters()), critic_factory(self.critic.parameters())]
        if self.lr_batch_rule is not None:
            for optimizer, name in zip(optimizers, ("model.map_optimizer", "model.critic_optimizer")):
                self.lr_batch_rule.apply(optimizer, self.trainer.datamodule.batch_size, name)
        schedulers = [f(opt) for f, opt in zip(self.scheduler_factories, optimizers) if f is not None]
        for scheduler in schedulers:
            if getattr(scheduler, "total_steps", 0) is None:  # a schedule over the whole run
                scheduler.total_steps = int(self.trainer.estimated_stepping_batches)
        return (optimizers, schedulers) if schedulers else optimizers

    # --- evaluation on the joint sets ---------------------------------------------------
    def setup(self, stage: str) -> None:
        if self.draw_seed is None:
            self.draw_seed = torch.initial_seed()

    def on_fit_start(self) -> None:
        self._fit_clock = time.perf_counter()
        self.restored_step = self.loaded_from = None  # training moves on from the loaded checkpoint

    def on_train_start(self) -> None:
        self.sigterm.install(self.trainer)
        self._steps = self.trainer.estimated_stepping_batches
        plan_solves(self._steps - self.trainer.global_step)  # a long run compiles its solves at once

    def on_train_end(self) -> None:
        plan_solves(0)

    def on_train_batch_start(self, batch: Any, batch_idx: int) -> None:
        without_gradient_sync(self.trainer.strategy)
        new_training_step(self.device)
        self._validate_last_step()

    def on_train_batch_end(self, outputs: Any, batch: Any, batch_idx: int) -> None:
        self.sigterm.agree(self.trainer)

    def _validate_last_step(self) -> None:
        """Validate the run's last step also where ``trainer.val_check_interval`` does not divide the run's steps, so
        that its weights can be the best checkpoint: Lightning validates, and its loggers write, the step of a fit
        that is asked to stop (``trainer.should_stop``), and the budget ends the fit after this step anyway. Asked
        before the step, so that the step logs its own figures (:meth:`_logs_this_step`)."""
        trainer, every, step = self.trainer, self.trainer.val_check_batch, self.trainer.global_step + 1
        if step >= self._steps and every not in (None, math.inf) and step % every != 0:
            trainer.should_stop = True

    def on_validation_epoch_start(self) -> None:
        self._key_draws("val")

    def on_test_epoch_start(self) -> None:
        self._key_draws("test")

    def validation_step(self, batch: dict[str, Tensor], batch_idx: int) -> dict[str, Tensor]:
        return {"y_hat": self._evaluation_draws(batch, "validation")}

    def test_step(self, batch: dict[str, Tensor], batch_idx: int) -> dict[str, Tensor]:
        return {"y_hat": self._evaluation_draws(batch, "test")}

    def _evaluation_draws(self, batch: dict[str, Tensor], stage: str) -> Tensor:
        """The map's draws for an evaluation batch; a map whose solve diverges there stops the run with a diagnosis."""
        try:
            return self.generate(batch["x"], batch["x0"], batch["theta"], batch["y"].shape[1], signals=batch.get("signals"))
        except SimulationDiverged as error:  # the weights are those of a diverged map: no checkpoint of them
            checkpoint = self.trainer.checkpoint_callback
            last = Path(checkpoint.dirpath) / "last.ckpt" if checkpoint is not None and checkpoint.dirpath else None
            saved = str(last) if last is not None and last.exists() else None  # that of the previous validation
            what = f"the map's solve gave NaN/Inf on the {stage} inputs ({error})"
            raise TrainingDiverged(diagnosis(what, "map", self._learning_rates(), saved)) from None

    def on_validation_epoch_end(self) -> None:
        """Log training progress next to the metrics (those come from :class:`otgb.callbacks.Evaluation`)."""
        if self._fit_clock is not None and not self.trainer.sanity_checking:
            elapsed = self.elapsed_before + time.perf_counter() - self._fit_clock
            self.log("val/wall_time_s", elapsed, sync_dist=True)
            self.log("val/simulations", float(self.trainer.datamodule.simulations), sync_dist=True)

    def on_save_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        elapsed = self.elapsed_before + (time.perf_counter() - self._fit_clock if self._fit_clock else 0.0)
        checkpoint["otgb"] = {
            "map_updates": self.map_updates,
            "elapsed_s": elapsed,
            "draw_seed": self.draw_seed,
            "skipped_steps": self.guard.skipped,
        }

    def on_load_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        """Restore the counters (the draws are keyed by the global step: :attr:`generator`)."""
        self.restored_step = checkpoint.get("global_step")
        state = checkpoint.get("otgb", {})
        self.map_updates = state.get("map_updates", 0)
        self.elapsed_before = state.get("elapsed_s", 0.0)
        self.draw_seed = state.get("draw_seed", self.draw_seed)
        self.guard.skipped = state.get("skipped_steps", 0)
        self._generator = None


def _inputs(batch: dict[str, Tensor], k: int) -> dict[str, Tensor]:
    """The map's inputs of a training item's ``k``-th source batch: x, x0, theta and, for a driven model, signals."""
    return {key: batch[key][k] for key in ("x", "x0", "theta", "signals") if key in batch}
