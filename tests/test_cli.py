"""Real `otgb` runs through LightningCLI on tiny budgets."""

import csv
import json
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml
from lightning import Callback
from logcapture import records_of, text_of

from otgb.callbacks import progress
from otgb.callbacks.progress import SimulationProgressBar
from otgb.cli import main
from otgb.command import OTGBCLI, BestAndLastCheckpoint, logger_override
from otgb.data import SimulationDataModule
from otgb.errors import InputError
from otgb.reports import summary_of
from otgb.runs import load_run
from otgb.training import MapTraining

ROOT = Path(__file__).parents[1]
CONFIG = str(ROOT / "configs" / "pendulum.yaml")
CONFIGS = sorted((ROOT / "configs").glob("*.yaml"))


def _args(tmp_path: Path, *extra: str, config: str = CONFIG) -> list[str]:
    return [
        "--config",
        config,
        logger_override(str(tmp_path), "run"),
        "--trainer.enable_progress_bar=false",
        "--trainer.val_check_interval=3",
        "--trainer.log_every_n_steps=1",
        "--data.simulation_budget=3200",
        "--data.batch_size=16",
        "--data.n_measured=64",
        "--data.n_val=24",
        "--data.n_test=20",
        f"--data.cache_dir={tmp_path / 'cache'}",
        *extra,
    ]


def _rows(run_dir: Path) -> list[dict]:
    with open(run_dir / "metrics.csv") as f:
        return list(csv.DictReader(f))


def _last(rows: list[dict], key: str) -> float:
    return [float(r[key]) for r in rows if r.get(key)][-1]


def test_fit_writes_logs_checkpoints_and_figures(tmp_path, capsys):
    main(
        [
            "fit",
            *_args(tmp_path, "--trainer.max_steps=6", "--model.t_max=5", "--model.ema_decay=0.9", "--evaluation.tests_every=2"),
        ]
    )
    run = tmp_path / "run" / "version_0"
    last = capsys.readouterr().out.strip().splitlines()[-1]
    assert last == f"otgb fit: results in {run}: config.yaml, metrics.csv, checkpoints/, figures/, components.json", last
    assert {"metrics.csv", "config.yaml", "hparams.yaml"} <= {p.name for p in run.iterdir()}
    assert list(run.glob("events.out.tfevents.*")), "TensorBoard events next to the CSV log"
    assert (run / "checkpoints" / "last.ckpt").is_file() and list(run.glob("checkpoints/best-*.ckpt"))
    figures = sorted(p.name for p in (run / "figures").iterdir())
    assert figures == ["components.png", "trajectories_step0000003.png", "trajectories_step0000006.png"]
    assert json.loads((run / "components.json").read_text())["traj_err_kind"] == "abs_err", "the component analysis ran"
    rows = _rows(run)
    assert _last(rows, "val/fp_nrmse") > 0.1, "the uncorrected f_p gap is logged"
    assert len([r for r in rows if r.get("val/abs_err")]) == 2, "cheap metrics at every validation"
    assert len([r for r in rows if r.get("val/c2st")]) == 1 and len([r for r in rows if r.get("val/mmdagg_pvalue")]) == 1
    ckpt = torch.load(run / "checkpoints" / "last.ckpt", weights_only=False)
    assert ckpt["global_step"] == 6, "global_step counts Algorithm-1 iterations, not optimizer steps"
    assert ckpt["otgb"]["map_updates"] == 30
    assert ckpt["SimulationDataModule"]["items_consumed"] == 6
    weights = ckpt["state_dict"]
    assert weights["map_average.n_averaged"] == 30, "the moving average follows every map update"
    name = "transport_map.correction.out.weight"
    assert not torch.equal(weights[name], weights[f"map_average.module.{name.split('.', 1)[1]}"])


def test_budget_ends_training_and_sets_the_schedule_length(tmp_path):
    schedule = ["--model.map_scheduler=otgb.schedules.CosineOverRun", "--model.map_scheduler.final_factor=0.1"]
    main(["fit", *_args(tmp_path, "--data.simulation_budget=480", "--model.t_max=5", *schedule)])  # 480 / (16 * 5) = 6 steps
    ckpt = torch.load(tmp_path / "run" / "version_0" / "checkpoints" / "last.ckpt", weights_only=False)
    assert ckpt["global_step"] == 6 and ckpt["SimulationDataModule"]["items_consumed"] == 6
    scheduler = ckpt["lr_schedulers"][0]
    assert scheduler["total_steps"] == 6 and scheduler["last_epoch"] == 6
    assert scheduler["_last_lr"][0] == pytest.approx(0.1 * scheduler["base_lrs"][0])


def test_the_last_step_is_validated_where_the_interval_does_not_divide_the_run(tmp_path):
    main(["fit", *_args(tmp_path, "--data.simulation_budget=560", "--model.t_max=5")])  # 560 / (16 * 5) = 7 steps
    run = tmp_path / "run" / "version_0"
    assert [int(float(r["step"])) for r in _rows(run) if r.get("val/abs_err")] == [2, 5, 6], "steps 3, 6 and the last, 7"
    assert torch.load(run / "checkpoints" / "last.ckpt", weights_only=False)["global_step"] == 7
    assert (run / "figures" / "trajectories_step0000007.png").is_file()


def test_the_batch_rule_scales_both_learning_rates_before_the_schedules_start(tmp_path):
    rule = ["--model.lr_batch_rule=otgb.schedules.BatchScaledRate", "--model.lr_batch_rule.reference_batch=4"]
    rule.append("--model.lr_batch_rule.exponent=-0.5")
    main(["fit", *_args(tmp_path, "--trainer.max_steps=2", "--data.batch_size=16", *rule)])  # 16 / 4: rates halved
    ckpt = torch.load(tmp_path / "run" / "version_0" / "checkpoints" / "last.ckpt", weights_only=False)
    configured = yaml.safe_load((ROOT / "otgb" / "configs" / "defaults.yaml").read_text())["model"]
    for scheduler, optimizer in zip(ckpt["lr_schedulers"], ("map_optimizer", "critic_optimizer")):
        assert scheduler["base_lrs"][0] == pytest.approx(0.5 * configured[optimizer]["init_args"]["lr"])


def test_a_batch_the_rule_cannot_serve_is_one_line_naming_the_rate_and_its_range(tmp_path, capsys):
    rule = ["--model.lr_batch_rule=otgb.schedules.BatchScaledRate", "--model.lr_batch_rule.reference_batch=64"]
    rule.append("--model.lr_batch_rule.exponent=-0.5")
    with pytest.raises(SystemExit) as exit_info:
        main(["fit", *_args(tmp_path, "--trainer.max_steps=2", "--data.batch_size=4", *rule)])  # 1e-3 * 4 = 4e-3
    assert exit_info.value.code == 2
    last = capsys.readouterr().err.splitlines()[-1]
    assert last.startswith("otgb: error: model.lr_batch_rule: model.map_optimizer's learning rate 0.001 scaled to batch 4")
    assert "outside the stable range [1e-05, 0.002]" in last
    assert not (tmp_path / "run").exists(), "nothing written"


def test_resume_continues_the_stream_and_matches_an_uninterrupted_run(tmp_path, recwarn):
    main(["fit", *_args(tmp_path / "a", "--trainer.max_steps=6", "--model.t_max=5")])
    stop = '--trainer.callbacks+={"class_path": "conftest.StopAt", "init_args": {"step": 3}}'
    main(["fit", *_args(tmp_path / "b", "--trainer.max_steps=6", "--model.t_max=5"), stop])
    last = tmp_path / "b" / "run" / "version_0" / "checkpoints" / "last.ckpt"
    main(["fit", *_args(tmp_path / "b", "--trainer.max_steps=6", "--model.t_max=5"), f"--ckpt_path={last}"])
    full = torch.load(tmp_path / "a" / "run" / "version_0" / "checkpoints" / "last.ckpt", weights_only=False)
    resumed = torch.load(tmp_path / "b" / "run" / "version_1" / "checkpoints" / "last.ckpt", weights_only=False)
    assert resumed["global_step"] == 6 and resumed["SimulationDataModule"]["items_consumed"] == 6
    assert resumed["otgb"]["map_updates"] == 30
    best, resumed_best = (next(v for k, v in c["callbacks"].items() if "BestAndLastCheckpoint" in k) for c in (full, resumed))
    assert resumed_best["best_model_score"] == best["best_model_score"], "the resumed run keeps the earlier best to beat"
    assert Path(resumed_best["best_model_path"]).name == Path(best["best_model_path"]).name
    for name, value in full["state_dict"].items():
        assert torch.allclose(value, resumed["state_dict"][name], atol=1e-5), name
    messages = [str(w.message) for w in recwarn]
    assert not [m for m in messages if "not resumable" in m or "will be deleted" in m], "the causes are fixed"


def test_a_resume_into_a_new_folder_keeps_the_best_score_to_beat(tmp_path):
    earlier = BestAndLastCheckpoint(dirpath=tmp_path / "version_0" / "checkpoints", monitor="val/abs_err", save_last=True)
    best = str(tmp_path / "version_0" / "checkpoints" / "best-step=3.ckpt")
    earlier.best_k_models = {best: torch.tensor(0.1)}
    earlier.best_model_path, earlier.best_model_score = best, torch.tensor(0.1)
    earlier.kth_best_model_path, earlier.kth_value = earlier.best_model_path, torch.tensor(0.1)
    resumed = BestAndLastCheckpoint(dirpath=tmp_path / "version_1" / "checkpoints", monitor="val/abs_err", save_last=True)
    resumed.load_state_dict(earlier.state_dict())
    assert float(resumed.best_model_score) == pytest.approx(0.1) and resumed.best_model_path == earlier.best_model_path
    assert resumed.best_k_models == earlier.best_k_models and float(resumed.kth_value) == pytest.approx(0.1)
    assert resumed.last_model_path == "", "last.ckpt is the new folder's"


def test_same_seed_same_numbers(tmp_path):
    for run in ("a", "b"):
        main(["fit", *_args(tmp_path / run, "--trainer.max_steps=3")])
    a, b = (_rows(tmp_path / r / "run" / "version_0") for r in ("a", "b"))
    assert _last(a, "val/abs_err") == _last(b, "val/abs_err")
    assert _last(a, "train/critic_loss") == _last(b, "train/critic_loss")


def test_training_figures_are_written_every_log_every_n_steps(tmp_path):
    """The step's figures reach Lightning only at the steps its loggers write: those steps all have them."""
    main(["fit", *_args(tmp_path, "--trainer.max_steps=7", "--trainer.log_every_n_steps=2")])
    rows = [r for r in _rows(tmp_path / "run" / "version_0") if r.get("train/map_loss")]
    assert [int(r["step"]) for r in rows] == [1, 3, 5, 6], "every second step, and the last (validated: 7 = 2 x 3 + 1)"
    for key in ("train/map_loss", "train/critic_loss", "train/map_updates", "train/simulations"):
        assert all(np.isfinite(float(r[key])) for r in rows), key
    assert [float(r["train/map_updates"]) for r in rows] == [2.0, 4.0, 6.0, 7.0], "each written figure is its own step's"


def test_test_subcommand_and_overrides(tmp_path):
    main(["fit", *_args(tmp_path, "--trainer.max_steps=3", "--model.objective.gamma=0.0", "--model.gp_weight=0.5")])
    run = tmp_path / "run" / "version_0"
    assert "gp_weight: 0.5" in (run / "config.yaml").read_text()
    main(["test", *_args(tmp_path), f"--ckpt_path={run / 'checkpoints' / 'last.ckpt'}"])
    rows = _rows(tmp_path / "run" / "version_1")
    assert _last(rows, "test/abs_err") > 0 and _last(rows, "test/fp_abs_err") > 0.1
    main(["validate", *_args(tmp_path), f"--ckpt_path={run / 'checkpoints' / 'last.ckpt'}"])
    assert _last(_rows(tmp_path / "run" / "version_2"), "val/abs_err") == _last(_rows(run), "val/abs_err")


@pytest.mark.parametrize(
    "override, message",
    [
        (["--model.objective.gamma=1.0"], "model.objective.gamma=1.0 > 0 needs n_z >= 2"),
        (["--model.critic_steps=0"], "critic_steps >= 1.*critic_steps=0"),
        (["--model.latent=categorical", "--model.z_dim=1", "--model.n_z=2"], "categorical.*needs z_dim >= 2, got 1"),
        (["--evaluation.c2st_precision=bf16"], "c2st_precision='bf16'.*expected one of .*'bf16-mixed'"),
        (["--evaluation.c2st_classifier=svm"], "c2st_classifier='svm'.*expected one of .*'mlp'"),
        (["--data.measurement_noise=-0.1"], r"data.measurement_noise=-0.1: expected a standard deviation >= 0"),
        (["--data.measurement_noise=0.05"], r"measurement_noise=0.05 applies to measurements read from a file"),
    ],
)
def test_bad_config_value_is_named(tmp_path, override, message):
    with pytest.raises(ValueError, match=message):
        OTGBCLI(MapTraining, SimulationDataModule, args=["fit", *_args(tmp_path, *override)])


def _otgb(cwd: Path, *args: str) -> subprocess.CompletedProcess:
    """``python -m otgb.cli ...`` in ``cwd``, importing this checkout's otgb (and the tests' callbacks)."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), str(ROOT / "tests"), os.environ.get("PYTHONPATH", "")])}
    return subprocess.run([sys.executable, "-m", "otgb.cli", *args], cwd=cwd, env=env, capture_output=True, text=True)


def test_progress_written_to_a_file_is_whole_lines_up_to_the_last_step(tmp_path):
    """Not a terminal: the progress is plain lines (a bar's redraws would pile up into one long line)."""
    args = [a for a in _args(tmp_path, "--trainer.max_steps=6") if a != "--trainer.enable_progress_bar=false"]
    done = _otgb(tmp_path, "fit", *args)
    assert done.returncode == 0, done.stderr[-2000:]
    assert "\r" not in done.stdout
    lines = [line for line in done.stdout.splitlines() if line.startswith("step ")]
    assert [line.split(" |")[0] for line in lines] == [f"step {n}/6 ({100 * n / 6:.0f}%)" for n in range(1, 7)], lines
    assert "to go" in lines[2] and lines[-1].endswith("simulations 96/3200"), lines


def test_the_time_to_go_counts_the_steps_a_resumed_run_has_run_at_the_rate_since_its_first_line(monkeypatch):
    bar = SimulationProgressBar(lines=True)
    bar._started, bar._first_step = 100.0, 500  # resumed at step 500
    clock = iter([160.0, 170.0, 100.0 + 3900])
    monkeypatch.setattr(progress, "perf_counter", lambda: next(clock))
    line = bar.progress_line(600, 1000, {"v_num": 0, "train/wasserstein": 0.123456, "simulations": "9600/16000"})
    assert line == "step 600/1000 (60%) | 1m00s, about 4m00s to go | train/wasserstein 0.1235 | simulations 9600/16000"
    assert "1m10s, about 30s to go" in bar.progress_line(700, 1000, {}), "a start-up cost (a compile) is not paid again"
    assert "1h05m, about 1h04m to go" in bar.progress_line(800, 1000, {})


def test_bad_input_is_one_line_status_2_and_no_run_directory(tmp_path):
    done = _otgb(tmp_path, "fit", "--config", CONFIG, "--model.objective.gamma=1.0", f"--data.cache_dir={tmp_path / 'cache'}")
    assert done.returncode == 2
    message = "otgb: error: model.objective.gamma=1.0 > 0 needs n_z >= 2 latent draws per source (got n_z=1)"
    assert done.stderr.splitlines() == [message]
    assert not (tmp_path / "runs").exists()


@pytest.mark.parametrize(
    "args, last",
    [
        (["--data.simulation_budgit=640"], "unknown option --data.simulation_budgit (did you mean --data.simulation_budget?)"),
        (
            ["--data.physics=otgb.physics.Pendulm"],
            "--data.physics: no class 'otgb.physics.Pendulm' (did you mean otgb.physics.Pend",
        ),
        (
            ["--model.transport_map.class_path=otgb.models.GreyBoxOD"],  # a class given for a callable
            "--model.transport_map: no class 'otgb.models.GreyBoxOD' (did you mean otgb.models.GreyBoxODE",
        ),
        (["--model.objective.gama=1"], "--model.objective: otgb.ot.WeakTransport has no option 'gama' (did you mean gamma?)"),
        (["--data.simulation_budget=abc"], "--data.simulation_budget: expected int, got abc"),
        (["--config", "bad.yaml"], "unknown key 'data.simulation_budgit' (did you mean data.simulation_budget?) in bad.yaml"),
        (["--trainer.max_step=3"], "unknown option --trainer.max_step (did you mean --trainer.max_steps"),  # no abbreviations
        (
            ["--config", "friction.yaml"],  # a misspelt option of a class inside a list
            "--data.hidden_effect: otgb.physics.ViscousFriction has no option 'xii' (did you mean xi?) in friction.yaml",
        ),
        (
            ["--config", "constant.yaml"],  # ... and of a class inside that class
            "--data.hidden_effect: xi: otgb.physics.Constant has no option 'valu' (did you mean value?) in constant.yaml",
        ),
        (
            ["--config", "correction.yaml"],  # a class given to a callable inside another class's arguments
            "--model.transport_map: correction: otgb.models.ConditionalMLP has no option 'hiden' (did you mean hidden?) "
            "in correction.yaml",
        ),
        (  # a command-line typo is not blamed on the config file, which holds 'xi' elsewhere
            ["--model.critic.init_args.xi=3"],
            "--model.critic: otgb.models.MLPCritic has no option 'xi'; list the options",
        ),
        (
            ["--config", "critic.yaml"],
            "--model.critic: otgb.models.MLPCritic has no option 'hiden' (did you mean hidden?) in critic.yaml",
        ),
        (  # a file that sets only init_args: the class is the config's, named after the option in the error
            ["--config", "critic_args.yaml"],
            "--model.critic: otgb.models.MLPCritic has no option 'hiden' (did you mean hidden?) in critic_args.yaml",
        ),
        (["--config", "critc.yaml"], "--config: no such file '{tmp_path}/critc.yaml' (did you mean critic.yaml"),
        (["--trainer.accelerator=gpux"], "trainer: You selected an invalid accelerator name"),
        (["--trainer.precision=bf16-mixed"], "--trainer.precision=bf16-mixed: otgb trains in float32 (expected 32-true)"),
        (["--model.objective.gamma=-1"], "model.objective.gamma=-1.0: expected a value in [0, 1]"),  # raised while built
        (
            ["--model.lr_batch_rule=otgb.schedules.BatchScaledRate", "--model.lr_batch_rule.max_lr=0"],
            "model.lr_batch_rule: need reference_batch >= 1 and 0 < min_lr < max_lr",
        ),
    ],
)
def test_parser_errors_are_a_few_lines_ending_with_the_closest_names(tmp_path, monkeypatch, capsys, args, last):
    (tmp_path / "bad.yaml").write_text("data:\n  simulation_budgit: 5\n")
    effect = "data:\n  hidden_effect:\n    - class_path: otgb.physics.ViscousFriction\n      init_args:\n        {}:\n"
    constant = "          class_path: otgb.physics.Constant\n          init_args: {{{}: 1.2}}\n"
    (tmp_path / "friction.yaml").write_text(effect.format("xii") + constant.format("value"))
    (tmp_path / "constant.yaml").write_text(effect.format("xi") + constant.format("valu"))
    critic = "model:\n  critic:\n    class_path: otgb.models.MLPCritic\n    init_args: {hiden: [5]}\n"
    (tmp_path / "critic.yaml").write_text(critic)
    (tmp_path / "critic_args.yaml").write_text("model:\n  critic:\n    init_args: {hiden: [5]}\n")
    correction = "model:\n  transport_map:\n    init_args:\n      correction:\n        class_path: otgb.models.ConditionalMLP\n"
    (tmp_path / "correction.yaml").write_text(correction + "        init_args: {hiden: [64, 64]}\n")
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as exit_info:
        main(["fit", "--config", CONFIG, f"--data.cache_dir={tmp_path / 'cache'}", *args])
    lines = capsys.readouterr().err.splitlines()
    assert exit_info.value.code == 2 and len(lines) <= 3, lines
    assert lines[-1].startswith(f"otgb: error: {last.format(tmp_path=tmp_path)}"), lines[-1]
    assert not (tmp_path / "runs").exists(), "nothing written"


def test_a_budget_that_ends_before_the_first_validation_is_one_line_and_nothing_written(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as exit_info:
        main(["fit", "--config", CONFIG, "--data.simulation_budget=1000", f"--data.cache_dir={tmp_path / 'cache'}"])
    last = capsys.readouterr().err.splitlines()[-1]
    assert exit_info.value.code == 2
    assert last == (
        "otgb: error: trainer.val_check_interval=125: data.simulation_budget=1000 gives only 31 training steps (32 "
        "simulations a step on each of 1 process(es)); expected a budget of at least 4000 or "
        "--trainer.val_check_interval <= 31"
    )
    assert not (tmp_path / "runs").exists(), "nothing written"


def test_a_saved_config_that_pins_a_taken_version_is_refused_and_the_run_kept(tmp_path, monkeypatch, capsys):
    main(["fit", *_args(tmp_path, "--trainer.max_steps=3")])
    run = tmp_path / "run" / "version_0"
    kept = {path: path.read_bytes() for path in run.rglob("*") if path.is_file()}
    for command in (["fit"], ["test", f"--ckpt_path={run / 'checkpoints' / 'last.ckpt'}"]):
        with pytest.raises(SystemExit) as exit_info:
            main([command[0], "--config", str(run / "config.yaml"), *command[1:]])
        assert exit_info.value.code == 2
        last = capsys.readouterr().err.splitlines()[-1]
        assert last.startswith(f"otgb: error: trainer.logger version 0: {run} already holds a run; expected a version")
    assert {path: path.read_bytes() for path in run.rglob("*") if path.is_file()} == kept
    assert [p.name for p in (tmp_path / "run").iterdir()] == ["version_0"]
    loaded = load_run(run / "config.yaml", ckpt_path=run / "checkpoints" / "last.ckpt")  # loading writes nothing: taken
    trained = torch.load(run / "checkpoints" / "last.ckpt", weights_only=False)["state_dict"]
    assert all(torch.equal(v, trained[k]) for k, v in loaded.model.state_dict().items() if k in trained)
    assert {path: path.read_bytes() for path in run.rglob("*") if path.is_file()} == kept


class BadInputAtSetup(Callback):
    """Raises InputError once the trainer has started, as a bad measured-data file would."""

    def setup(self, trainer, pl_module, stage) -> None:
        raise InputError("bad input found at setup")


def test_bad_input_after_the_logger_started_removes_its_run_directory(tmp_path, capsys):
    (tmp_path / "run" / "version_0").mkdir(parents=True)  # an earlier run stays
    callback = '--trainer.callbacks+={"class_path": "test_cli.BadInputAtSetup"}'
    with pytest.raises(SystemExit) as exit_info:
        main(["fit", *_args(tmp_path, callback)])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err.splitlines()  # after the trainer started, Lightning's own warnings may come first
    assert err[-1] == "otgb: error: bad input found at setup" and sum(line.startswith("otgb:") for line in err) == 1
    assert [p.name for p in (tmp_path / "run").iterdir()] == ["version_0"]


def test_console_script_print_config():
    out = subprocess.run(
        [sys.executable, "-m", "otgb.cli", "fit", "--config", CONFIG, "--model.t_max=7", "--print_config"],
        capture_output=True,
        text=True,
        check=True,
    ).stdout
    assert "t_max: 7" in out
    assert "batches_per_step" not in out, "linked from model.t_max, so not a setting of its own"
    assert "class_path: otgb.physics.Pendulum" in out


@pytest.mark.slow
def test_one_to_many_config_selects_on_joint_c2st(tmp_path):
    config = str(Path(CONFIG).with_name("pendulum_mm.yaml"))
    evaluation = ["--evaluation.reference_repeats=2", "--evaluation.mmdagg_permutations=200"]
    main(["fit", *_args(tmp_path, "--trainer.max_steps=6", *evaluation, config=config)])
    run = tmp_path / "run" / "version_0"
    rows = _rows(run)
    assert len([r for r in rows if r.get("val/c2st") and r.get("val/mmd")]) == 2, "selection metric at each validation"
    best = next(run.glob("checkpoints/best-*.ckpt"))
    scores = {int(float(r["step"])) + 1: float(r["val/c2st"]) for r in rows if r.get("val/c2st")}
    assert best.name == f"best-step={min(scores, key=scores.get)}.ckpt"
    assert _last(rows, "val/fp_mmd") > 10 * _last(rows, "val/ref_mmd"), "f_p alone is far above the noise floor"
    assert _last(rows, "val/fp_c2st") > 0.8 and _last(rows, "val/fp_mmdagg_reject") == 1.0
    assert not any(r.get("val/abs_err") for r in rows), "pointwise errors are meaningless for one-to-many"
    ckpt = torch.load(run / "checkpoints" / "last.ckpt", weights_only=False)
    assert ckpt["hyper_parameters"]["n_z"] == 10
    assert "gamma: 1.0" in (run / "config.yaml").read_text()


def test_test_writes_metrics_json_and_table(tmp_path, capsys):
    main(["fit", *_args(tmp_path, "--trainer.max_steps=3")])
    ckpt = tmp_path / "run" / "version_0" / "checkpoints" / "last.ckpt"
    capsys.readouterr()
    main(["test", *_args(tmp_path, "--evaluation.reference_repeats=2"), f"--ckpt_path={ckpt}"])
    captured = capsys.readouterr()
    summary, last = captured.out.strip().splitlines()[-2:]
    assert last.startswith(f"otgb test: results in {tmp_path / 'run' / 'version_1'}: metrics.md, metrics.json"), last
    assert summary.startswith("otgb test: C2ST accuracy: model ") and "Reference (noise floor)" in summary, summary
    assert "Test metric" not in captured.out + captured.err, "the results are in metrics.md, not a raw metric table"
    report = json.loads((tmp_path / "run" / "version_1" / "metrics.json").read_text())
    assert report["run"]["ckpt_path"] == str(ckpt) and report["run"]["global_step"] == 3 and report["run"]["n_inputs"] == 20
    assert report["reference"]["abs_err"] == {"mean": 0.0, "std": 0.0}, "a one-to-one DGP has no noise floor"
    assert report["fp"]["abs_err"]["mean"] > 0.1 and report["model"]["abs_err"]["std"] > 0
    assert report["reference"]["c2st"]["mean"] == 0.5, "identical DGP draws cannot be told apart"
    assert report["fp"]["c2st"]["mean"] > 0.7 and report["fp"]["mmdagg_reject"]["mean"] == 1.0
    table = (tmp_path / "run" / "version_1" / "metrics.md").read_text()
    assert "| ABS ERR | lower |" in table and "| C2ST accuracy | 0.5: cannot be told apart; 1: always can |" in table
    assert "| MMDAgg rejects H0 (alpha 0.05) | no (yes: the samples differ) | " in table, "a test's decision reads yes / no"
    assert "| yes | " in table and "of splits |" in table, "f_p is rejected; the Reference's rejection rate over splits"
    assert table.count("C2ST accuracy: model ") == 1 and "of f_p's distance to the noise floor." in table, "one summary"


def test_checkpoint_on_a_test_metric_needs_tests_at_every_validation(tmp_path, capsys):
    config = str(Path(CONFIG).with_name("pendulum_2m.yaml"))
    with pytest.raises(SystemExit) as exit_info:
        main(["fit", *_args(tmp_path, "--trainer.max_steps=3", "--evaluation.tests_every=2", config=config)])
    assert exit_info.value.code == 2
    assert re.search(r"^otgb: error: .*monitor='val/c2st'.*evaluation.tests_every=2", capsys.readouterr().err, re.M)


def test_checkpoint_must_monitor_a_metric_of_the_mode(tmp_path, capsys):
    """A measured file has no DGP: a checkpoint on val/abs_err is refused before training, with the choices."""
    measured = tmp_path / "m.npz"
    np.savez(measured, y=np.zeros((100, 50, 1)))
    args = _args(tmp_path, "--data.hidden_effect=[]", f"--data.measured_path={measured}", "--checkpoint.monitor=val/abs_err")
    with pytest.raises(SystemExit):
        main(["fit", *args])
    assert "the marginal evaluation does not log it; choose one of ['val/mmd', 'val/mmd2_median', 'val/energy'" in (
        capsys.readouterr().err
    )


def _tiny(config: Path, cache: Path) -> list[str]:
    """Overrides that make any config a seconds-long run: 4 steps, validation at 2 and 4, small sets."""
    tiny = ["--trainer.enable_progress_bar=false", "--trainer.max_steps=4", "--trainer.val_check_interval=2"]
    tiny += ["--trainer.log_every_n_steps=1", "--data.batch_size=4", "--data.n_measured=24", "--data.n_val=12"]
    tiny += ["--data.n_test=12", f"--data.cache_dir={cache}", "--evaluation.reference_repeats=1"]
    tiny += ["--evaluation.c2st_folds=2", "--evaluation.mmdagg_permutations=200"]
    data = yaml.safe_load(config.read_text()).get("data") or {}
    if data.get("measured_step_size") is not None:
        tiny.append("--data.measured_step_size=0.01")  # the same fields to 2e-6 (README), 10x fewer steps
    if data.get("draws_per_input", 1) > 1:
        tiny.append("--data.draws_per_input=2")
    return tiny


@pytest.mark.parametrize("config", CONFIGS, ids=lambda path: path.stem)
def test_config_fits_and_tests(tmp_path, monkeypatch, config):
    """Every config in configs/ trains and tests through the CLI on a tiny budget, with its own run name."""
    monkeypatch.chdir(tmp_path)
    tiny = _tiny(config, tmp_path / "cache")
    main(["fit", "--config", str(config), *tiny])
    run = tmp_path / "runs" / config.stem / "version_0"
    assert {"metrics.csv", "config.yaml", "hparams.yaml"} <= {p.name for p in run.iterdir()}
    assert list(run.glob("events.out.tfevents.*")), "TensorBoard events next to the CSV log"
    figures = sorted(p.name.split("_", 1)[-1] for p in (run / "figures").iterdir())
    assert figures == ["components.png", "step0000002.png", "step0000004.png"], "validation figures and the component analysis"
    monitor = yaml.safe_load((run / "config.yaml").read_text())["checkpoint"]["monitor"]
    assert monitor.startswith("val/"), "checkpoint.monitor: auto is resolved in the saved config"
    rows = _rows(run)
    scores = {int(float(r["step"])) + 1: float(r[monitor]) for r in rows if r.get(monitor)}
    assert sorted(scores) == [2, 4] and _last(rows, "val/fp_mmd") > 0
    best = [p.name for p in run.glob("checkpoints/best-*.ckpt")]
    assert best == [f"best-step={min(scores, key=scores.get)}.ckpt"], "the best checkpoint is chosen on the monitor"
    ckpt = torch.load(run / "checkpoints" / "last.ckpt", weights_only=False)
    assert ckpt["global_step"] == 4, "last.ckpt is the latest validation, whether best or not"
    checkpoints = [state for key, state in ckpt["callbacks"].items() if key.startswith("BestAndLastCheckpoint")]
    assert [state["monitor"] for state in checkpoints] == [monitor], "the checkpoint used the resolved monitor"
    main(["test", "--config", str(config), *tiny, f"--ckpt_path={run / 'checkpoints' / 'last.ckpt'}"])
    report = json.loads((tmp_path / "runs" / config.stem / "version_1" / "metrics.json").read_text())
    assert report["run"]["n_inputs"] == 12 and report["run"]["global_step"] == 4 and report["model"]["c2st"]["mean"] >= 0
    data = torch.load(next((tmp_path / "cache").glob("test-*.pt")), weights_only=True)
    assert data["y"].shape[0] == 12 and data["y"].shape[2:] == data["x"].shape[1:]


@pytest.mark.parametrize("task, overlay", [("pendulum_2m", "pendulum"), ("advdiff_mm", "advdiff")])
def test_separable_correction_overlay_fits_and_tests(tmp_path, monkeypatch, task, overlay):
    """configs/separable/*.yaml swap a task's free correction for a separable one, through the CLI."""
    monkeypatch.chdir(tmp_path)
    config = ROOT / "configs" / f"{task}.yaml"
    configs = ["--config", str(config), "--config", str(ROOT / "configs" / "separable" / f"{overlay}.yaml")]
    tiny = _tiny(config, tmp_path / "cache")
    main(["fit", *configs, *tiny])
    run = tmp_path / "runs" / f"{task}-{overlay}" / "version_0"
    saved = yaml.safe_load((run / "config.yaml").read_text())["model"]["transport_map"]["init_args"]["correction"]
    assert saved["class_path"] == "otgb.models.SeparableCorrection" and saved["init_args"]["rank"] == 1
    weights = torch.load(run / "checkpoints" / "last.ckpt", weights_only=False)["state_dict"]
    assert any(".correction.coefficients." in key for key in weights) and any(".correction.basis." in key for key in weights)
    assert torch.isfinite(torch.tensor(_last(_rows(run), "val/mmd")))
    main(["test", *configs, *tiny, f"--ckpt_path={run / 'checkpoints' / 'last.ckpt'}"])
    report = json.loads((tmp_path / "runs" / f"{task}-{overlay}" / "version_1" / "metrics.json").read_text())
    assert 0 <= report["model"]["c2st"]["mean"] <= 1 and report["model"]["mmd"]["mean"] >= 0


@pytest.mark.parametrize(
    "config, override, monitor",
    [
        ("pendulum", [], "val/abs_err"),  # deterministic DGP: pointwise error
        ("advdiff_mm", [], "val/mmd"),  # stochastic DGP: MMD on joint samples
        ("pendulum", ["--checkpoint.monitor=val/mmd"], "val/mmd"),
        ("pendulum_mm", [], "val/c2st"),  # set in the task file
    ],
)
def test_checkpoint_monitor_auto_follows_the_measured_process(tmp_path, config, override, monitor):
    args = _args(tmp_path, *override, config=str(ROOT / "configs" / f"{config}.yaml"))
    cli = OTGBCLI(MapTraining, SimulationDataModule, run=False, args=args)
    assert cli.trainer.checkpoint_callback.monitor == monitor and cli.config.checkpoint.monitor == monitor
    assert cli.datamodule.selection_metric == ("val/mmd" if config != "pendulum" else "val/abs_err")
    assert cli.trainer.checkpoint_callback.save_last is True and cli.trainer.checkpoint_callback.filename == "best-{step}"


def test_own_config_gets_the_defaults_and_names_the_run(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    own = tmp_path / "elsewhere" / "my_pendulum.yaml"
    own.parent.mkdir()
    own.write_text(Path(CONFIG).read_text())
    delta = tmp_path / "slow_critic.yaml"
    delta.write_text("model:\n  critic_optimizer:\n    init_args: {lr: 1.0e-4}\n")
    for configs, name in [([own], "my_pendulum"), ([own, delta], "my_pendulum-slow_critic")]:
        args = [arg for path in configs for arg in ("--config", str(path))]
        cli = OTGBCLI(MapTraining, SimulationDataModule, run=False, args=args)
        assert cli.model.map_average is not None and cli.model.t_max == 1, "model settings of the defaults file"
        assert [(logger.name, logger.version) for logger in cli.trainer.loggers] == [(name, 0), (name, 0)]
        assert Path(cli.trainer.loggers[0].log_dir) == Path("runs") / name / "version_0"
    assert cli.config.model.critic_optimizer.init_args.lr == 1.0e-4 and cli.config.model.map_optimizer.init_args.lr == 1.0e-3
    named = OTGBCLI(MapTraining, SimulationDataModule, run=False, args=["--config", str(own), logger_override("logs", "mine")])
    assert [logger.name for logger in named.trainer.loggers] == ["mine", "mine"], "a logger named by the user keeps its name"


def test_a_run_whose_loggers_write_to_two_folders_says_so_in_one_line(tmp_path, monkeypatch):
    """``--trainer.logger.init_args.save_dir`` moves only the last logger of the list: the run says where each went."""
    monkeypatch.chdir(tmp_path)
    args = ["--config", CONFIG, "--trainer.logger.init_args.save_dir=elsewhere"]
    with records_of("lightning.pytorch") as records:
        cli = OTGBCLI(MapTraining, SimulationDataModule, run=False, args=args)
    folders = [Path(logger.log_dir).parent.parent for logger in cli.trainer.loggers]
    assert folders == [Path("runs"), Path("elsewhere")]
    lines = [r.getMessage() for r in records if "loggers write to" in r.getMessage()]
    assert len(lines) == 1 and "runs/pendulum/version_0" in lines[0] and "elsewhere/pendulum/version_0" in lines[0], lines


@pytest.mark.parametrize(
    "max_steps, every, first", [(3, "100", 100), (200, "100", None), (50, "0.5", 1562), (2000, "0.5", None), (-1, "100", None)]
)
def test_a_run_stopped_before_its_first_validation_says_so(tmp_path, monkeypatch, max_steps, every, first):
    """An int val_check_interval counts steps, a float is a fraction of the run (3125 steps of the config's budget)."""
    monkeypatch.chdir(tmp_path)
    args = ["--config", CONFIG, f"--trainer.max_steps={max_steps}", f"--trainer.val_check_interval={every}"]
    with records_of("lightning.pytorch") as records:
        cli = OTGBCLI(MapTraining, SimulationDataModule, run=False, args=args)
        cli.before_fit()
    lines = [r.getMessage() for r in records if "before its first validation" in r.getMessage()]
    expected = f"otgb: --trainer.max_steps={max_steps} ends the run before its first validation (at step {first} of the budget's"
    assert lines == [] if first is None else len(lines) == 1 and lines[0].startswith(expected), lines


def test_categorical_latent_draws_equally_likely_one_hot_codes(tmp_path):
    config = str(Path(CONFIG).with_name("pendulum_2m.yaml"))
    args = _args(tmp_path, "--model.latent=categorical", "--model.z_dim=3", config=config)
    model = OTGBCLI(MapTraining, SimulationDataModule, run=False, args=args).model
    n = 3000
    z = model.sample_z(n)
    assert z.shape == (n, 3) and set(z.unique().tolist()) == {0.0, 1.0} and torch.all(z.sum(1) == 1)
    counts = z.sum(0)
    assert torch.all((counts - n / 3).abs() <= 3 * (n * (1 / 3) * (2 / 3)) ** 0.5), counts


def test_a_fit_prints_no_known_harmless_third_party_lines(tmp_path):
    """otgb.quiet drops Lightning's cloud-logger tip, its TPU line, its note on counting steps and its "max_epochs=1
    reached" when the budget is spent; its GPU line stays."""
    command = [sys.executable, "-m", "otgb.cli", "fit", "--config", CONFIG, "--data.simulation_budget=64"]
    command += ["--trainer.val_check_interval=2"]
    command.append(f"--data.cache_dir={tmp_path}")
    done = subprocess.run(command, cwd=tmp_path, capture_output=True, text=True, timeout=600)
    printed = done.stdout + done.stderr
    assert done.returncode == 0 and "GPU available" in printed, printed[-2000:]
    for harmless in ("litlogger", "TPU available", "to estimate number of stepping batches", "max_epochs=1"):
        assert harmless not in printed, harmless
    assert done.stdout.splitlines()[-1].startswith("otgb fit: results in "), "the budget spent, the run says where it wrote"


def test_load_run_builds_the_model_and_data_of_a_run_quietly(tmp_path, capfd):
    main(["fit", *_args(tmp_path, "--trainer.max_steps=2")])
    ckpt = tmp_path / "run" / "version_0" / "checkpoints" / "last.ckpt"
    capfd.readouterr()
    run = load_run(CONFIG, *_args(tmp_path)[2:], "--data.batch_size", "8", ckpt_path=ckpt)
    assert capfd.readouterr().err == "", "nothing printed: no evaluation line, no seed line, no warning"
    assert run.datamodule.batch_size == 8, "the overrides, in order"
    saved = torch.load(ckpt, weights_only=False)["state_dict"]
    assert all(torch.equal(saved[k], v) for k, v in run.model.state_dict().items()), "the checkpoint's weights"
    with pytest.raises(InputError, match="no such checkpoint file"):
        load_run(CONFIG, ckpt_path=tmp_path / "missing.ckpt")
    assert sorted(p.name for p in (tmp_path / "run").iterdir()) == ["version_0"], "nothing written"


def test_load_run_takes_a_test_runs_saved_config_and_writes_neither_into_that_run_nor_its_options(tmp_path):
    main(["fit", *_args(tmp_path, "--trainer.max_steps=2")])
    ckpt = tmp_path / "run" / "version_0" / "checkpoints" / "last.ckpt"
    main(["test", *_args(tmp_path), f"--ckpt_path={ckpt}"])
    tested = tmp_path / "run" / "version_1" / "config.yaml"
    assert "verbose" in yaml.safe_load(tested.read_text()), "a test run's config holds the test command's verbose"
    kept = {path: path.read_bytes() for path in tmp_path.joinpath("run").rglob("*") if path.is_file()}
    run = load_run(tested, "--trainer.max_steps=2", ckpt_path=ckpt)
    run.trainer.fit(run.model, run.datamodule)  # as otgb tune trains a trial, or a notebook goes on from a run
    assert Path(run.trainer.log_dir) == tmp_path / "run" / "version_2", "the next free version, not the loaded run's"
    assert {path: path.read_bytes() for path in kept} == kept, "the runs it was loaded from, as they were"
    saved = Path(run.trainer.log_dir) / "config.yaml"
    assert not {"verbose", "ckpt_path"} & set(yaml.safe_load(saved.read_text())), "the test's command-only options"
    main(["fit", "--config", str(saved), logger_override(str(tmp_path / "refit"), "run"), "--trainer.max_steps=2"])
    assert list((tmp_path / "refit" / "run").glob("version_*/checkpoints/last.ckpt")), "otgb fit takes the saved config"


def test_a_second_run_reads_f_p_and_the_reference_from_the_cache_and_gives_the_same_numbers(tmp_path):
    with records_of("lightning.pytorch") as records:
        main(["fit", *_args(tmp_path, "--trainer.max_steps=3")])
    assert len(list((tmp_path / "cache").glob("baselines-*.pt"))) == 1, "the validation set's f_p and Reference scores"
    said = text_of(records)
    assert "read from" not in said and "scoring f_p alone and the Reference on this set (once: kept in" in said
    with records_of("lightning.pytorch") as records:
        main(["fit", *_args(tmp_path, "--trainer.max_steps=3")])
    said = text_of(records)
    assert f"the Reference on this set: read from {tmp_path / 'cache'}/baselines-" in said
    assert "scoring f_p alone" not in said
    timing = ("eval_seconds", "wall_time_s")
    first, second = (_rows(tmp_path / "run" / f"version_{v}") for v in (0, 1))
    assert _last(second, "val/ref_eval_seconds") == 0.0 < _last(first, "val/ref_eval_seconds"), "read, not scored"
    strip = lambda rows: [{k: v for k, v in row.items() if not k.endswith(timing)} for row in rows]  # noqa: E731
    assert strip(first) == strip(second), "the same numbers, the model's included: reading the cache draws nothing"
    assert _last(second, "val/fp_c2st") > 0.5 and _last(second, "val/fp_mmd") > 0


def _report(tmp_path: Path, version: int) -> str:
    return (tmp_path / "run" / f"version_{version}" / "metrics.md").read_text()


def test_test_without_a_checkpoint_says_it_scores_an_untrained_map_and_f_p_alone_does_not(tmp_path):
    untrained = "otgb test: no checkpoint: scoring the map as initialised, untrained"
    with records_of("lightning.pytorch") as records:
        main(["test", *_args(tmp_path, "--evaluation.reference_repeats=1")])
        assert untrained in text_of(records)
        assert "**Note: no checkpoint was given, so the model is the map as initialised" in _report(tmp_path, 0)
        assert "no checkpoint was given" in summary_of(tmp_path / "run" / "version_0"), "the closing sentence says it too"
        records.clear()
        main(["test", *_args(tmp_path, "--evaluation.reference_repeats=1", "--model.transport_map=otgb.models.IdentityMap")])
        assert untrained not in text_of(records), "nothing to train: nothing to say"
        assert "no checkpoint was given" not in _report(tmp_path, 1) and "no checkpoint (step 0)" in _report(tmp_path, 1)
        main(["fit", *_args(tmp_path, "--trainer.max_steps=3")])
        records.clear()
        last = next(tmp_path.rglob("last.ckpt"))
        main(["test", *_args(tmp_path, "--evaluation.reference_repeats=1"), f"--ckpt_path={last}"])
        assert untrained not in text_of(records) and "otgb: evaluation mode" in text_of(records)
        records.clear()
        run = load_run(tmp_path / "run" / "version_2" / "config.yaml", ckpt_path=last)  # docs/runs.md's Python way
        run.trainer.test(run.model, run.datamodule, verbose=False)
        assert untrained not in text_of(records) and "no checkpoint was given" not in _report(tmp_path, 4)
        assert f"checkpoint `{last}` (step 3)" in _report(tmp_path, 4)


def test_a_misspelt_key_reads_the_same_from_discover_as_from_fit(tmp_path, monkeypatch, capsys):
    """discover's parser reports a key inside a group ('batch_sise' of 'data'); the line names it in full, as fit's."""
    (tmp_path / "bad.yaml").write_text("data:\n  simulation_budgit: 5\n")
    monkeypatch.chdir(tmp_path)
    for command, extra in (("fit", []), ("discover", ["--data.measured_path=m.csv"])):
        with pytest.raises(SystemExit) as exit_info:
            main([command, "--config", CONFIG, "--config", "bad.yaml", *extra])
        line = capsys.readouterr().err.splitlines()[-1]
        assert exit_info.value.code == 2
        assert line == (
            "otgb: error: unknown key 'data.simulation_budgit' (did you mean data.simulation_budget?) in bad.yaml; "
            f"list the options with: otgb {command} --help"
        )
    assert not (tmp_path / "runs").exists(), "nothing written"
