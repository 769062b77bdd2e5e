"""Where the time of one training step goes: simulation, map solve, critic, backward.

    python scripts/profile_step.py --config configs/pendulum.yaml [--steps 20] [--batch-size 64] [--solver compiled]
        [--device cuda] [--trace 25] [--model.critic.init_args.channels=[8,16] ...]

Builds the model and data module from the config (as `otgb fit` would), then times the
parts of Algorithm 1 on real batches: the f_p simulation of a step's source batches, the
grey-box forward solves, the map backward passes, and the critic update (forward, penalty,
backward). Prints mean milliseconds per training step, each part's share (the share of
"simulate f_p" is the fraction of a step spent simulating) and f_p's simulations per second.
The first two steps (where a compiled solve compiles) are timed apart, as the warm-up. Other
arguments are the run's config overrides, as ``otgb fit`` takes them.
``--device cuda`` runs on the GPU, each part timed to the end of its kernels. ``--trace N``
then profiles two more steps with ``torch.profiler`` (without those timing synchronisations)
and prints its N operators of most time (on the device where there is one, else on the host),
with the number of scalars read back from the device (on a GPU, each a synchronisation).
"""

from __future__ import annotations

import argparse
import time
from collections import defaultdict
from contextlib import contextmanager

import torch
from lightning.pytorch.utilities import move_data_to_device

from otgb.data import SimulationDataModule
from otgb.ot import critic_loss
from otgb.physics.solvers import SOLVERS, current_solver
from otgb.runs import load_run
from otgb.training import MapTraining


def build(config: str, overrides: list[str]) -> tuple[MapTraining, SimulationDataModule]:
    run = load_run(config, "--trainer.logger=false", *overrides)
    return run.model, run.datamodule


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--config", required=True)
    parser.add_argument("--steps", type=int, default=20)
    parser.add_argument("--batch-size", type=int, default=None, help="source batch size (default: the config's)")
    parser.add_argument("--solver", choices=SOLVERS, default="compiled", help="the solve path (otgb fit's --solver)")
    parser.add_argument("--device", default="cpu", help="where the model and its batches live (cpu, cuda)")
    parser.add_argument("--trace", type=int, default=0, help="profile two more steps and print this many operators")
    args, config_overrides = parser.parse_known_args()
    overrides = [f"--solver={args.solver}", *config_overrides]
    overrides += [] if args.batch_size is None else [f"--data.batch_size={args.batch_size}"]
    model, dm = build(args.config, overrides)  # the run's --solver is set as `otgb fit` sets it
    dm.setup("fit")
    device = torch.device(args.device)
    model.to(device)
    map_opt = torch.optim.Adam(model.transport_map.parameters(), lr=1e-4)
    critic_opt = torch.optim.Adam(model.critic.parameters(), lr=1e-4)
    stream = iter(dm.train_dataloader())
    times: dict[str, float] = defaultdict(float)

    synchronise = [device.type == "cuda"]  # each part timed to the end of its kernels; off under the trace

    @contextmanager
    def timed(name: str):
        start = time.perf_counter()
        yield
        if synchronise[0]:
            torch.cuda.synchronize(device)
        times[name] += time.perf_counter() - start

    def step() -> None:
        with timed("sample (x0, theta)"):
            batch = move_data_to_device(next(stream), device)
        with timed("simulate f_p"):
            batch = dm.on_after_batch_transfer(batch, 0)
        for k in range(model.t_max):
            x, x0, theta = batch["x"][k], batch["x0"][k], batch["theta"][k]
            with timed("map forward (grey-box solve)"):
                y_hat = model.generate(x, x0, theta, model.n_z)
            with timed("map loss (cost + critic)"):
                loss, _ = model.objective.map_loss(x, y_hat, model.critic)
            map_opt.zero_grad()
            with timed("map backward"):
                loss.backward()
            with timed("optimizer steps"):
                map_opt.step()
        with timed("critic forward + penalty"):
            generated = y_hat.detach().flatten(0, 1)
            loss, _ = critic_loss(model.critic, batch["y"][0], generated, model.gp_weight, one_sided=model.gp_one_sided)
        critic_opt.zero_grad()
        with timed("critic backward"):
            loss.backward()
        with timed("optimizer steps"):
            critic_opt.step()

    warmup = 0.0
    for index in range(args.steps + 2):
        if index == 2:  # the first steps warm up allocators and caches, and compile the solves
            warmup = sum(times.values())
            times.clear()
        step()
    total = sum(times.values())
    print(
        f"{args.config}: {1000 * total / args.steps:.1f} ms per training step (T_max = {model.t_max}, batch {dm.batch_size}, "
        f"threads {torch.get_num_threads()}, solver {current_solver()}); the 2 warm-up steps took {warmup:.1f} s"
    )
    for name, seconds in sorted(times.items(), key=lambda kv: -kv[1]):
        print(f"  {name:32s} {1000 * seconds / args.steps:8.1f} ms  {100 * seconds / total:5.1f} %")
    rate = args.steps * dm.batch_size * model.t_max / times["simulate f_p"]
    print(f"f_p simulations per second (batch {dm.batch_size}): {rate:.0f}")
    if args.trace:
        synchronise[0] = False
        print_trace(step, device, args.trace)


def print_trace(step, device: torch.device, rows: int) -> None:
    """Two steps under ``torch.profiler``: the ``rows`` operators of most self time, and the scalars read back from
    the device (``.item()`` and the like: on a GPU, each waits for every kernel before it)."""
    activities = [torch.profiler.ProfilerActivity.CPU]
    if device.type == "cuda":
        activities.append(torch.profiler.ProfilerActivity.CUDA)
    with torch.profiler.profile(activities=activities) as profile:
        for _ in range(2):
            step()
    events = profile.key_averages()
    sort = "self_cuda_time_total" if device.type == "cuda" else "self_cpu_time_total"
    print(events.table(sort_by=sort, row_limit=rows, max_name_column_width=60))
    reads = sum(e.count for e in events if e.key == "aten::_local_scalar_dense")
    print(f"scalar reads from the device in 2 steps: {reads} (on a GPU each is a host-device synchronisation)")


if __name__ == "__main__":
    main()
