"""The source stream: fresh draws of (x0, theta) for f_p, under a simulation budget.

Every item is a pure function of (seed, rank, item index) (counter-based seeding), so the
stream's whole state is the number of items consumed: a resumed run restarts at that
index and replays nothing. Ranks draw from disjoint keys and split the budget; workers of
one rank take the items i = start + worker_id, start + worker_id + num_workers, ..., which
the DataLoader hands back in index order.

One item is one iteration of Algorithm 1: ``batches_per_step`` source batches of
``batch_size`` inputs (one per map update, and one per critic update after the first)
and ``measured_batches_per_step`` batches of measured trajectories (one per critic
update). The f_p simulation itself runs on the training device, in the data module.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator

import torch
from torch import Tensor
from torch.utils.data import DataLoader, IterableDataset, get_worker_info

from otgb.data.seeding import generator_for
from otgb.physics.base import PhysicsModel


class SourceStream(IterableDataset):
    """Yields dicts with ``index``, ``x0`` (K, B, *state), ``theta`` (K, B, P), ``y`` (K_y, B_y, T, *obs) and, for a
    driven model, ``signals`` (K, B, T_u, I), the inputs' signals of each simulation.

    Args:
        physics: f_p, whose priors are sampled.
        measured: the fixed measured set (N, T, *obs); batches are drawn with replacement.
        batch_size: B, source inputs per map update.
        batches_per_step: K, source batches per item.
        measured_batch_size: B_y, measured trajectories per critic update.
        measured_batches_per_step: K_y, critic updates per item.
        budget: simulations this rank may spend; the stream ends before exceeding it.
        seed: key of the random draws.
        rank: this process's rank, the draws' second key.
        start: first item index (resume).
    """

    def __init__(
        self,
        physics: PhysicsModel,
        measured: Tensor,
        batch_size: int,
        batches_per_step: int,
        measured_batch_size: int,
        measured_batches_per_step: int,
        budget: int,
        seed: int,
        rank: int = 0,
        start: int = 0,
    ) -> None:
        super().__init__()
        self.physics, self.measured = physics, measured
        self.batch_size, self.batches_per_step = batch_size, batches_per_step
        self.measured_batch_size, self.measured_batches_per_step = measured_batch_size, measured_batches_per_step
        self.budget = budget
        self.seed, self.rank, self.start = seed, rank, start

    @property
    def simulations_per_item(self) -> int:
        return self.batch_size * self.batches_per_step

    @property
    def end(self) -> int:
        """One past the last item index: where the budget ends the run."""
        return self.budget // self.simulations_per_item

    def __len__(self) -> int:
        """Items in the whole run, those before ``start`` included: Lightning counts a resumed run's
        batches on from where the checkpoint left them, so its progress bar and epoch end match."""
        return self.end

    def __iter__(self) -> Iterator[dict[str, Tensor | int]]:
        info = get_worker_info()
        worker, workers = (info.id, info.num_workers) if info is not None else (0, 1)
        for index in range(self.start + worker, self.end, workers):
            yield self.item(index)

    def item(self, index: int) -> dict[str, Tensor | int]:
        g = generator_for(self.seed, "source", self.rank, index)
        n, k = self.simulations_per_item, self.batches_per_step
        x0 = self.physics.sample_initial_state(n, g)
        theta = self.physics.sample_theta(n, g)
        pick = torch.randint(len(self.measured), (self.measured_batches_per_step, self.measured_batch_size), generator=g)
        signals = self.physics.sample_signals(n, g)
        item = {
            "index": index,
            "x0": x0.reshape(k, self.batch_size, *x0.shape[1:]),
            "theta": theta.reshape(k, self.batch_size, -1),
            "y": self.measured[pick],
        }
        return item if signals is None else {**item, "signals": signals.reshape(k, self.batch_size, *signals.shape[1:])}


class StreamLoader(DataLoader):
    """The DataLoader of a :class:`SourceStream`, resumable in Lightning's sense (``state_dict`` /
    ``load_state_dict``): its state is the number of items consumed (``position()``, the data
    module's count), and restoring it restarts the stream there."""

    def __init__(self, stream: SourceStream, position: Callable[[], int], num_workers: int = 0) -> None:
        super().__init__(stream, batch_size=None, num_workers=num_workers)
        self.position = position

    def state_dict(self) -> dict[str, int]:
        return {"items_consumed": self.position()}

    def load_state_dict(self, state_dict: dict[str, int]) -> None:
        self.dataset.start = int(state_dict["items_consumed"])
