"""Measurement files (.pt/.npz/.csv), their split, and the data module's two modes."""

import csv
import logging

import numpy as np
import pytest
import torch
from logcapture import records_of

from otgb.data import SimulationDataModule, read_measured, split_indices
from otgb.data.times import on_common_times
from otgb.errors import InputError
from otgb.physics import AdvectionDiffusion, Constant, Pendulum, ViscousFriction


@pytest.fixture
def measurements(damped, generator):
    """40 friction-pendulum trajectories with the inputs they were simulated with."""
    x0, theta = damped.sample_initial_state(40, generator), damped.sample_theta(40, generator)
    y = damped.simulate(x0, theta, damped.sample_effect_params(40, generator))
    return {"y": y, "t": damped.times(), "theta": theta, "x0": x0}


def write_csv(path, content, columns=("trajectory", "t", "angle", "omega", "x0_angle", "x0_velocity")):
    with open(path, "w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(columns)
        for i in range(len(content["y"])):
            for k, t in enumerate(content["t"].tolist()):
                values = {
                    "trajectory": i,
                    "t": t,
                    "angle": float(content["y"][i, k, 0]),
                    "omega": float(content["theta"][i, 0]),
                    "x0_angle": float(content["x0"][i, 0]),
                    "x0_velocity": float(content["x0"][i, 1]),
                }
                writer.writerow([values[c] for c in columns])


def test_the_three_formats_read_the_same_content(tmp_path, pendulum, measurements):
    torch.save(measurements, tmp_path / "m.pt")
    np.savez(tmp_path / "m.npz", **{k: v.numpy() for k, v in measurements.items()})
    write_csv(tmp_path / "m.csv", measurements)
    torch.save(measurements["y"], tmp_path / "y_only.pt")
    for name in ("m.pt", "m.npz", "m.csv"):
        content = read_measured(tmp_path / name, pendulum)
        assert content.recorded_inputs == ("theta", "x0"), name
        assert torch.allclose(content.y, measurements["y"]) and torch.allclose(content.theta, measurements["theta"])
        assert torch.allclose(content.x0, measurements["x0"]), name
    assert read_measured(tmp_path / "y_only.pt", pendulum).recorded_inputs == ()


def test_csv_keeps_trajectories_in_file_order_and_reads_partial_inputs(tmp_path, pendulum, measurements):
    write_csv(tmp_path / "m.csv", measurements, columns=("t", "angle", "trajectory", "omega"))
    rows = (tmp_path / "m.csv").read_text().splitlines()
    header, body = rows[0], rows[1:]
    shuffled = body[50:100] + body[:50] + body[100:]  # trajectory 1 first
    (tmp_path / "s.csv").write_text("\n".join([header, *shuffled]) + "\n")
    content = read_measured(tmp_path / "s.csv", pendulum)
    assert content.recorded_inputs == ("theta",)
    assert torch.allclose(content.y[0], measurements["y"][1]) and torch.allclose(content.y[1], measurements["y"][0])


BAD_CONTENT = {
    "wrong shape": (
        {"y": torch.randn(12, 40, 1)},
        r"'y': measured trajectories have shape \(12, 40, 1\), expected \(N, 50, 1\) on",
    ),
    "wrong obs": ({"y": torch.randn(12, 50, 2)}, r"'y': measured trajectories have shape \(12, 50, 2\), expected \(N, T, 1\)"),
    "empty": ({"y": torch.zeros(0, 50, 1)}, "no trajectories"),
    "nan": (
        {"y": torch.full((3, 50, 1), float("nan"))},
        r"trajectory 0 has 0 measured time\(s\) with a value, expected at least 3 \(3 of 3",
    ),
    "inf": (
        {"y": torch.tensor([0.0, float("inf")]).repeat(3, 25)[..., None]},
        r"trajectory 0: an infinite value, expected finite",
    ),
    "t shape": (
        {"y": torch.randn(3, 50, 1), "t": torch.zeros(2, 50)},
        r"'t' has shape \(2, 50\), expected \(50,\) .* or \(3, 50\)",
    ),
    "decreasing": (
        {"y": torch.randn(2, 3, 1), "t": torch.tensor([[0.0, 0.2, 0.1], [0.0, 0.1, 0.2]])},
        r"trajectory 0: times not increasing, t=0.1 after t=0.2",
    ),
    "value without time": (
        {"y": torch.randn(2, 4, 1), "t": torch.tensor([[0.0, 0.1, 0.2, float("nan")], [0.0, 0.1, 0.2, 0.3]])},
        r"trajectory 0: a value without a time \(NaN in 't'\)",
    ),
    "missing key": ({"z": torch.randn(3, 50, 1)}, r"unknown entries \['z'\]"),
    "no y": ({"t": torch.arange(50.0)}, "no entry 'y'"),
    "bool dtype": ({"y": torch.ones(3, 50, 1, dtype=torch.bool)}, "'y' has dtype (torch.)?bool, expected real numbers"),
    "grid": ({"y": torch.randn(3, 50, 1), "t": torch.arange(50.0) * 0.2}, r"trajectory 0: t=5 lies outside the model's horizon"),
    "theta width": ({"y": torch.randn(3, 50, 1), "theta": torch.ones(3, 2)}, r"'theta' has shape \(3, 2\), expected \(3, 1\)"),
    "theta inf": (
        {"y": torch.randn(3, 50, 1), "theta": torch.tensor([[1.0], [float("inf")], [1.0]])},
        r"NaN/Inf in 1 of 3 rows, the first at position 1",
    ),
    "x0 shape": ({"y": torch.randn(3, 50, 1), "x0": torch.ones(3, 1)}, r"'x0' has shape \(3, 1\), expected \(3, 2\)"),
}


@pytest.mark.parametrize("case", sorted(BAD_CONTENT))
def test_bad_files_are_named_in_one_line(tmp_path, pendulum, case):
    content, match = BAD_CONTENT[case]
    torch.save(content, tmp_path / "m.pt")
    np.savez(tmp_path / "m.npz", **{k: v.numpy() for k, v in content.items()})
    for name in ("m.pt", "m.npz"):
        with pytest.raises(InputError, match=match) as error:
            read_measured(tmp_path / name, pendulum)
        assert str(tmp_path / name) in str(error.value) and "\n" not in str(error.value)


@pytest.mark.parametrize(
    "text, match",
    [
        ("", "the file is empty"),
        ("trajectory,t,angle\n", "a header but no rows"),
        ("trajectory,t,angel\n0,0,1\n", r"missing \['angle'\], unknown \['angel'\], did you mean 'angel' -> 'angle'\?;"),
        ("trajectory,t,angle,temperature\n0,0,1,2\n", r"header \[.*\]: unknown \['temperature'\]; expected columns"),
        ("trajectory,t,ANGLE\n0,0,1\n", r"did you mean 'ANGLE' -> 'angle'\?;"),
        ("trajectory,t,angle,angle_std\n0,0,1,0\n", r"header \[.*\]: unknown \['angle_std'\]; expected"),  # not 'angle' again
        ("trajectory,t,angle,t\n0,0,1,0\n", r"header \[.*\]: repeated \['t'\]; expected columns"),
        ("trajectory,t,angle\n0,0,1\n0,0.1\n", "line 3: 2 fields, expected 3"),
        ("trajectory,t,angle\n0,0,x\n", r"line 2: a field is not a number"),
        (
            "trajectory,t,angle\n0,0,1\n0,0.1,1\n0,0.2,1\n1,0,1\n",
            r"trajectory 1 has 1 measured time\(s\) with a value, expected at least 3",
        ),
        ("trajectory,t,angle\n4,0,1\n4,0.2,1\n4,0.1,1\n", r"trajectory 4: times not increasing, t=0.1 after t=0.2"),
        ("trajectory,t,angle\n4,0,1\n4,0.2,1\n4,7.5,1\n", r"trajectory 4: t=7.5 lies outside the model's horizon \[0, 4.9\]"),
        (
            "trajectory,t,angle\n4,0,1\n4,0.2,\n4,0.3,1\n",
            r"trajectory 4 has 2 measured time\(s\) with a value, expected at least 3",
        ),
        ("trajectory,t,angle,x0_angle\n0,0,1,1\n", r"\['x0_angle'\] given without \['x0_velocity'\]"),
    ],
)
def test_bad_csv_files_are_named(tmp_path, pendulum, text, match):
    (tmp_path / "m.csv").write_text(text)
    with pytest.raises(InputError, match=match):
        read_measured(tmp_path / "m.csv", pendulum)


def test_csv_checks_per_trajectory_values_and_fields(tmp_path, pendulum, measurements):
    write_csv(tmp_path / "m.csv", measurements, columns=("trajectory", "t", "angle", "omega"))
    lines = (tmp_path / "m.csv").read_text().splitlines()
    lines[3] = ",".join(lines[3].split(",")[:3] + ["9.9"])  # omega changes within trajectory 0
    (tmp_path / "v.csv").write_text("\n".join(lines) + "\n")
    with pytest.raises(InputError, match=r"\['omega'\] change within trajectory 0"):
        read_measured(tmp_path / "v.csv", pendulum)
    with pytest.raises(InputError, match="CSV holds low-dimensional series.*use a .npz or .pt"):
        read_measured(tmp_path / "m.csv", AdvectionDiffusion())


def test_missing_file_and_suffix(tmp_path, pendulum, monkeypatch):
    with pytest.raises(InputError, match="nope.npz' does not exist \\(expected"):
        read_measured(tmp_path / "nope.npz", pendulum)
    monkeypatch.chdir(tmp_path)
    with pytest.raises(InputError, match=f"'nope.csv' does not exist, looked for at '{tmp_path / 'nope.csv'}': a relative"):
        read_measured("nope.csv", pendulum)
    with pytest.raises(InputError, match="unsupported suffix '.h5'"):
        read_measured(tmp_path / "m.h5", pendulum)
    (tmp_path / "broken.pt").write_bytes(b"not a torch file")
    with pytest.raises(InputError, match="broken.pt: cannot be read as a PyTorch file"):
        read_measured(tmp_path / "broken.pt", pendulum)


def test_split_is_disjoint_seeded_and_sized():
    parts = split_indices(1000, 0.15, 0.15, seed=0, where="f")
    assert [len(parts[p]) for p in ("train", "val", "test")] == [700, 150, 150]
    joined = torch.cat(list(parts.values()))
    assert len(joined.unique()) == 1000
    assert all(torch.equal(parts[p], split_indices(1000, 0.15, 0.15, seed=0, where="f")[p]) for p in parts)
    assert not torch.equal(parts["val"], split_indices(1000, 0.15, 0.15, seed=1, where="f")["val"])
    with pytest.raises(InputError, match="f: 50 trajectories .* 34 train / 8 validation / 8 test.*>= 10"):
        split_indices(50, 0.15, 0.15, seed=0, where="f")
    with pytest.raises(InputError, match=r"data.val_fraction=1.2: expected a fraction in \(0, 1\)"):
        split_indices(100, 1.2, 0.1, seed=0, where="f")


def _module(tmp_path, **kw):
    args = dict(physics=Pendulum(), n_val=6, n_test=5, batch_size=8, simulation_budget=800, cache_dir=str(tmp_path / "cache"))
    return SimulationDataModule(**{**args, **kw})


def test_marginal_mode_sets_never_overlap_and_the_file_is_untouched(tmp_path, measurements):
    path = tmp_path / "m.pt"
    torch.save({"y": measurements["y"]}, path)
    before = path.read_bytes()
    dm = _module(tmp_path, measured_path=str(path), val_fraction=0.25, test_fraction=0.25)
    assert dm.mode == "marginal" and dm.recorded_inputs == () and dm.dgp is None
    dm.setup("fit")
    dm.setup("test")
    assert len(dm.measured) == 20 and dm.val_set["y"].shape == (10, 1, 50, 1) and dm.test_set["y"].shape == (10, 1, 50, 1)
    rows = lambda t: {tuple(r.flatten().tolist()) for r in t}  # noqa: E731
    train, val, test = rows(dm.measured), rows(dm.val_set["y"][:, 0]), rows(dm.test_set["y"][:, 0])
    assert not (train & val) and not (train & test) and not (val & test)
    assert train | val | test == rows(measurements["y"])
    assert torch.allclose(dm.val_set["x"], dm.physics.simulate(dm.val_set["x0"], dm.val_set["theta"]))
    assert path.read_bytes() == before and not (tmp_path / "cache").exists(), "nothing written for a file"
    assert "20 train / 10 val / 10 test" in dm.describe()


def test_recorded_inputs_are_the_evaluation_inputs(tmp_path, measurements):
    np.savez(tmp_path / "m.npz", **{k: v.numpy() for k, v in measurements.items() if k != "x0"})
    dm = _module(tmp_path, measured_path=str(tmp_path / "m.npz"), val_fraction=0.25, test_fraction=0.25)
    dm.setup("validate")
    assert dm.recorded_inputs == ("theta",)
    val = dm.source.parts["val"]
    assert torch.equal(dm.val_set["theta"], measurements["theta"][val])
    assert torch.equal(dm.val_set["y"][:, 0], measurements["y"][val])
    assert not torch.equal(dm.val_set["x0"], measurements["x0"][val]), "x0 was not recorded: drawn from the prior"


def test_mode_settings_are_checked(tmp_path, measurements):
    torch.save(measurements["y"], tmp_path / "m.pt")
    friction = [ViscousFriction(Constant(1.2))]
    with pytest.raises(InputError, match="measured_path=.* and data.hidden_effect are both set"):
        _module(tmp_path, measured_path=str(tmp_path / "m.pt"), hidden_effect=friction)
    with pytest.raises(InputError, match="no measured data: set data.measured_path"):
        _module(tmp_path)
    assert _module(tmp_path, hidden_effect=friction).mode == "joint"


@pytest.mark.parametrize(
    "write, match",
    [
        (lambda p: p.write_text("\ufefftrajectory,t,angle\n" + "".join(f"0,{k / 10},0.1\n" for k in range(50)) + "\n\n"), None),
        (lambda p: p.write_text("trajectory,t,angle\nnan,0,0.1\n"), "line 2: the 'trajectory' column holds NaN/Inf"),
        (lambda p: p.write_text("trajectory,t,angle\nrun0,0,0.1\n"), "a field is not a number"),
        (  # a measurement is named by its line, trajectory id and time, not by its position in the file
            lambda p: p.write_text(
                "trajectory,t,angle\n"
                + "".join(f"{7 + i},{k / 10},{'nan' if (i, k) == (1, 3) else 0.1}\n" for i in range(2) for k in range(50))
            ),
            None,
        ),
        (
            lambda p: p.write_text(
                "trajectory,t,angle\n"
                + "".join(f"{7 + i},{k / 10},{'inf' if (i, k) == (1, 3) else 0.1}\n" for i in range(2) for k in range(50))
            ),
            r"m.csv, line 55: trajectory 8 at t=0.3: 'angle' is inf, expected a finite number \(an empty cell or NaN is a",
        ),
    ],
)
def test_csv_variants(tmp_path, pendulum, write, match):
    """A byte-order mark and trailing blank lines are fine, a NaN measurement is missing; a NaN or a word as an id and
    an infinite measurement are named."""
    write(tmp_path / "m.csv")
    if match is None:
        content = read_measured(tmp_path / "m.csv", pendulum)
        assert content.y.shape[1:] == (50, 1) and int(torch.isnan(content.y).sum()) == (len(content.y) == 2)
    else:
        with pytest.raises(InputError, match=match):
            read_measured(tmp_path / "m.csv", pendulum)


def test_npy_under_an_npz_name_and_a_folder(tmp_path, pendulum):
    with open(tmp_path / "m.npz", "wb") as handle:
        np.save(handle, np.zeros((3, 50, 1)))
    with pytest.raises(InputError, match="holds a single array"):
        read_measured(tmp_path / "m.npz", pendulum)
    (tmp_path / "folder.csv").mkdir()
    with pytest.raises(InputError, match="is not a file"):
        read_measured(tmp_path / "folder.csv", pendulum)


def test_each_source_gives_the_next_round_a_file_of_its_measurements(tmp_path, measurements):
    """Generated measurements are written once to measured.npz (the next round must not see the DGP); a file's own
    measurements are that file. Either way, data.measured_path reads them back."""
    friction = [ViscousFriction(Constant(1.2))]
    generated = _module(tmp_path, hidden_effect=friction).source
    (tmp_path / "round").mkdir()
    written = generated.as_file(tmp_path / "round", measurements["y"])
    assert written == str((tmp_path / "round" / "measured.npz").resolve())
    assert torch.equal(read_measured(written, Pendulum()).y, measurements["y"])
    path = tmp_path / "m.pt"
    torch.save({"y": measurements["y"]}, path)
    from_file = _module(tmp_path, measured_path=str(path), val_fraction=0.25, test_fraction=0.25).source
    assert from_file.as_file(tmp_path / "round", measurements["y"]) == str(path.resolve())
    assert (generated.selection_metric, from_file.selection_metric) == ("val/abs_err", "val/energy")
    assert generated.reference_on_same_inputs and not from_file.reference_on_same_inputs


def test_a_checkpoint_of_other_measurements_is_named_once_and_the_same_data_elsewhere_is_not(tmp_path, measurements):
    path = tmp_path / "m.pt"
    torch.save({"y": measurements["y"]}, path)
    np.savez(tmp_path / "moved.npz", y=measurements["y"].numpy())
    trained = _module(tmp_path, measured_path=str(path), val_fraction=0.25, test_fraction=0.25).state_dict()
    with records_of("otgb", level=logging.WARNING) as warned:
        same = _module(tmp_path, measured_path=str(tmp_path / "moved.npz"), val_fraction=0.25, test_fraction=0.25)
        same.load_state_dict(trained)
        assert same.trained_on is None and not warned, "the same trajectories and split under another name"
        resplit = _module(tmp_path, measured_path=str(path), val_fraction=0.25, test_fraction=0.25, seed=1)
        resplit.load_state_dict(trained)
        assert "; split differently (data.seed" in warned[-1].getMessage()
        generated = _module(tmp_path, hidden_effect=[ViscousFriction(Constant(1.2))])
        generated.load_state_dict(trained)
        generated.compare_with_training(trained)
        message = warned[-1].getMessage()
        assert len(warned) == 2, "one warning a run"
        assert message.startswith(f"otgb: the checkpoint was trained on the measurements in {path.resolve()}; this run uses ")
        assert "generated by the configured process (Pendulum + ViscousFriction(xi=Constant(value=1.2)" in message
        assert generated.trained_on
        other_friction = _module(tmp_path, hidden_effect=[ViscousFriction(Constant(0.5))])
        other_friction.load_state_dict(generated.state_dict())
        assert "Constant(value=0.5)" in warned[-1].getMessage() and "split differently" not in warned[-1].getMessage()


@pytest.mark.parametrize(
    "times, hint",
    [
        (
            np.arange(50) * 100.0,
            r"t=100 lies outside .* the file's step is 1000 x the model's dt, in another unit\? \(the model's is s\)$",
        ),
        (
            np.arange(50) * 0.2,
            r"t=5 lies outside the model's horizon \[0, 4.9\].*last until t=9.8; set data.physics.init_args.n_obs to 99",
        ),
        (np.float32(np.arange(100) * 0.1), r"set data.physics.init_args.n_obs to 100 to cover them$"),
        (
            np.arange(50) * 0.1 + 0.05,
            r"trajectory 0: t=4.95 lies outside the model's horizon \[0, 4.9\] \(physics dt=0.1, n_obs=50\)",
        ),
    ],
)
def test_times_outside_the_horizon_say_how(pendulum, times, hint):
    """Times in another unit or a longer recording: the error names the trajectory and the time and says which it looks
    like."""
    y = torch.zeros(2, len(times), 1)
    with pytest.raises(InputError, match=hint):
        on_common_times("lab.npz", y, torch.tensor(times), ["0", "1"], pendulum)


@pytest.mark.parametrize(
    "times",
    [np.arange(25) * 0.2, np.arange(25) * 0.1, np.arange(147) / 30, np.sort(np.random.default_rng(0).uniform(0, 4.9, 40))],
)
def test_times_inside_the_horizon_are_read_where_they_are(tmp_path, pendulum, times):
    """A file's own times inside the model's horizon: on the model's grid where every time is one of its observation
    times (the rest of the grid missing), else the model is read at the file's times."""
    y = torch.randn(3, len(times), 1)
    np.savez(tmp_path / "m.npz", y=y.numpy(), t=times)
    content = read_measured(tmp_path / "m.npz", pendulum)
    on_grid = bool(np.allclose(np.round(times * 10), times * 10))
    assert (content.times is None) == on_grid
    if on_grid:
        index = np.round(times * 10).astype(int)
        assert torch.equal(content.y[:, index], y) and int(torch.isnan(content.y).sum()) == 3 * (50 - len(times))
    else:
        assert torch.allclose(content.times, torch.tensor(times, dtype=torch.float64)) and torch.equal(content.y, y)


def test_own_times_per_trajectory_in_an_npz_meet_on_the_union_of_their_times(tmp_path, pendulum):
    """``t`` (N, T), NaN after a trajectory's last time: every trajectory on the union of the times, missing where it
    has no value."""
    t = np.array([[0.0, 0.05, 0.5, np.nan], [0.0, 0.3, 0.5, 1.25]])
    y = np.array([[1.0, 2.0, 3.0, np.nan], [4.0, 5.0, 6.0, 7.0]])[..., None]
    np.savez(tmp_path / "m.npz", y=y, t=t)
    content = read_measured(tmp_path / "m.npz", pendulum)
    assert torch.allclose(content.times, torch.tensor([0.0, 0.05, 0.3, 0.5, 1.25], dtype=torch.float64))
    nan = float("nan")
    expected = torch.tensor([[1.0, 2.0, nan, 3.0, nan], [4.0, nan, 5.0, 6.0, 7.0]])
    assert torch.allclose(content.y[..., 0], expected, equal_nan=True)
