from types import SimpleNamespace

import pytest
import torch
from torch.utils.data import DataLoader

from otgb.data import SimulationDataModule, SourceStream
from otgb.data.datamodule import check_measurement_noise
from otgb.errors import InputError
from otgb.physics import Constant, Pendulum, Uniform, ViscousFriction


def _stream(pendulum, **kw):
    args = dict(
        measured=torch.arange(1500.0).reshape(30, 50, 1),
        batch_size=4,
        batches_per_step=3,
        measured_batch_size=5,
        measured_batches_per_step=2,
        budget=100,
        seed=7,
    )
    return SourceStream(pendulum, **{**args, **kw})


def test_stream_item_shapes_and_budget(pendulum):
    stream = _stream(pendulum)
    items = list(stream)
    assert len(items) == len(stream) == 100 // 12 == 8
    assert items[0]["x0"].shape == (3, 4, 2) and items[0]["theta"].shape == (3, 4, 1) and items[0]["y"].shape == (2, 5, 50, 1)
    assert [it["index"] for it in items] == list(range(8))


def test_stream_length_is_the_runs_whole_length(pendulum):
    resumed = _stream(pendulum, start=3)
    assert len(resumed) == 8 and [it["index"] for it in resumed] == list(range(3, 8)), "counted from the run's start"


def test_stream_is_deterministic_resumable_and_rank_aware(pendulum):
    full = list(_stream(pendulum))
    again = list(_stream(pendulum))
    resumed = list(_stream(pendulum, start=5))
    other_rank = list(_stream(pendulum, rank=1))
    assert all(torch.equal(a["x0"], b["x0"]) and torch.equal(a["y"], b["y"]) for a, b in zip(full, again))
    assert len(resumed) == 3 and all(torch.equal(a["theta"], b["theta"]) for a, b in zip(full[5:], resumed))
    assert not torch.equal(full[0]["theta"], other_rank[0]["theta"])
    assert not torch.equal(full[0]["theta"], full[1]["theta"])


def test_workers_split_the_stream_without_replay(pendulum):
    single = list(DataLoader(_stream(pendulum), batch_size=None, num_workers=0))
    multi = list(DataLoader(_stream(pendulum), batch_size=None, num_workers=2))
    assert [int(b["index"]) for b in multi] == list(range(8))
    assert all(torch.equal(a["theta"], b["theta"]) for a, b in zip(single, multi))


def _module(tmp_path, **kw):
    args = dict(
        physics=Pendulum(),
        hidden_effect=[ViscousFriction(Constant(1.2))],
        n_measured=40,
        n_val=6,
        n_test=5,
        batch_size=8,
        simulation_budget=800,
        cache_dir=str(tmp_path / "cache"),
    )
    return SimulationDataModule(**{**args, **kw})


def test_sets_are_cached_and_regenerated_when_settings_change(tmp_path):
    dm = _module(tmp_path)
    dm.setup("fit")
    dm.setup("test")
    assert dm.measured.shape == (40, 50, 1) and dm.val_set["y"].shape == (6, 1, 50, 1) and dm.test_set["x"].shape == (5, 50, 1)
    files = sorted(p.name for p in (tmp_path / "cache").iterdir())
    assert len(files) == 3
    dm2 = _module(tmp_path)
    dm2.setup("fit")
    assert torch.equal(dm.measured, dm2.measured) and len(list((tmp_path / "cache").iterdir())) == 3
    changed = _module(tmp_path, hidden_effect=[ViscousFriction(Constant(0.5))])
    changed.setup("fit")
    assert not torch.equal(changed.measured, dm.measured) and len(list((tmp_path / "cache").iterdir())) == 5


def test_joint_sets_share_inputs_between_fp_and_dgp(tmp_path):
    dm = _module(tmp_path, hidden_effect=[ViscousFriction(Uniform(0.6, 1.5))], draws_per_input=4)
    dm.setup("validate")
    v = dm.val_set
    assert v["y"].shape == (6, 4, 50, 1)
    assert torch.equal(v["x"][:, 0], v["y"][:, 0, 0]) and torch.equal(v["x"][:, 0], v["x0"][:, :1])
    assert not torch.allclose(v["y"][:, 0], v["y"][:, 1]), "each draw has its own friction"
    assert torch.allclose(dm.physics.simulate(v["x0"], v["theta"]), v["x"])


def test_bad_config_values(tmp_path):
    with pytest.raises(ValueError, match="simulation_budget=5 is smaller than one training step"):
        _module(tmp_path, simulation_budget=5)
    with pytest.raises(ValueError, match="data.batch_size must be >= 1"):
        _module(tmp_path, batch_size=0)
    with pytest.raises(ValueError, match="data.measured_batch_size must be >= 1, got 0"):
        _module(tmp_path, measured_batch_size=0)
    for sd in (float("nan"), float("inf"), -1.0):
        with pytest.raises(ValueError, match=rf"data.measurement_noise={sd}: expected a standard deviation >= 0"):
            check_measurement_noise(sd, "measured.npz")


def test_evaluation_loaders_share_each_input_out_once_over_the_processes(tmp_path):
    dm = _module(tmp_path)
    dm.setup("test")  # 5 test inputs
    shares = []
    for rank in (0, 1):
        dm.trainer = SimpleNamespace(world_size=2, global_rank=rank)
        shares.append([i for batch in dm.test_dataloader() for i in batch["theta"][:, 0].tolist()])
    assert [len(share) for share in shares] == [3, 2], "no input repeated to even the shares"
    assert sorted(shares[0] + shares[1]) == sorted(dm.test_set["theta"][:, 0].tolist())
    dm.trainer = SimpleNamespace(world_size=6, global_rank=0)
    with pytest.raises(InputError, match="the test set has 5 inputs for 6 processes; expected at least one each"):
        dm.test_dataloader()


def test_state_dict_restores_the_stream_position(tmp_path):
    dm = _module(tmp_path)
    dm.setup("fit")
    batch = next(iter(dm.train_dataloader()))
    batch = dm.on_after_batch_transfer(batch, 0)
    assert batch["x"].shape == (1, 8, 50, 1) and dm.simulations == 8
    state = dm.state_dict()
    fresh = _module(tmp_path)
    fresh.setup("fit")
    fresh.load_state_dict(state)
    assert fresh.stream_seed == dm.stream_seed
    assert int(next(iter(fresh.train_dataloader()))["index"]) == 1
