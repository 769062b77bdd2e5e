"""The ``otgb`` command: LightningCLI over :class:`KernelWeakOT` and :class:`SimulationDataModule`.

    otgb fit --config configs/pendulum.yaml [--model.gamma 0.5 --trainer.max_steps 2000 ...]
    otgb validate|test --config configs/pendulum.yaml --ckpt_path runs/.../best.ckpt

The data module's f_p is handed to the model at instantiation, and the model's T_max sets
how many source batches each training item holds. The joint evaluation callback
(:class:`otgb.callbacks.Evaluation`) is always present; its settings are the config's
``evaluation:`` section (e.g. ``--evaluation.reference_repeats 10``). ``otgb test`` writes
``metrics.json`` and ``metrics.md`` into its run directory.
"""

from __future__ import annotations

from pathlib import Path

from lightning.pytorch.cli import LightningCLI

from otgb.callbacks import Evaluation
from otgb.data import SimulationDataModule
from otgb.training import KernelWeakOT


class OTGBCLI(LightningCLI):
    def add_arguments_to_parser(self, parser) -> None:
        parser.link_arguments("model.t_max", "data.batches_per_step")
        parser.link_arguments("data.physics", "model.physics", apply_on="instantiate")
        parser.add_lightning_class_args(Evaluation, "evaluation")

    def before_instantiate_classes(self) -> None:
        config = self.config[self.subcommand] if self.subcommand else self.config
        share_logger_version(config.trainer.logger)


def logger_override(save_dir: str, name: str) -> str:
    """A ``--trainer.logger`` argument for TensorBoard + CSV logs in ``<save_dir>/<name>/version_N``."""
    loggers = [
        f"{{class_path: lightning.pytorch.loggers.{cls}, init_args: {{save_dir: {save_dir}, name: {name}}}}}"
        for cls in ("TensorBoardLogger", "CSVLogger")
    ]
    return f"--trainer.logger=[{', '.join(loggers)}]"


def share_logger_version(loggers: object) -> None:
    """Give every configured logger that writes to the same <save_dir>/<name> one version.

    TensorBoard and CSV loggers each pick the next free ``version_N`` on their own, so the
    second one to start lands in a different folder; this picks N once for all of them.
    """
    if not isinstance(loggers, list):
        return
    groups: dict[Path, list] = {}
    for logger in loggers:
        args = getattr(logger, "init_args", None)
        if args is None or getattr(args, "version", None) is not None or getattr(args, "save_dir", None) is None:
            continue
        groups.setdefault(Path(args.save_dir) / (getattr(args, "name", None) or "lightning_logs"), []).append(args)
    for root, members in groups.items():
        taken = (
            [int(p.name.split("_")[1]) for p in root.glob("version_*") if p.name.split("_")[1].isdigit()] if root.is_dir() else []
        )
        version = max(taken, default=-1) + 1
        for args in members:
            args.version = version


def main(args: list[str] | None = None) -> None:
    OTGBCLI(KernelWeakOT, SimulationDataModule, args=args)


if __name__ == "__main__":
    main()
