"""A small convolutional classifier for C2ST on high-dimensional joint samples (PDE observations).

Each feature row is (conditioning inputs, trajectory): the first ``cond_dim`` features
(theta, x0) and then the trajectory of shape (T, C, *spatial) flattened. The trajectory goes
through two strided convolutions over (time, *spatial) with the C observed fields as
channels (Conv1d for (T, C), Conv2d for (T, C, X), Conv3d for (T, C, X, Y)), is pooled to a
fixed size and joined with an embedding of the conditioning inputs; an MLP head gives the
logit. It follows scikit-learn's estimator API, so ``cross_val_score`` can clone and fit it.
"""

from __future__ import annotations

import numpy as np
import torch
from sklearn.base import BaseEstimator, ClassifierMixin
from torch import Tensor, nn

CONV = {1: nn.Conv1d, 2: nn.Conv2d, 3: nn.Conv3d}
POOL = {1: nn.AdaptiveAvgPool1d, 2: nn.AdaptiveAvgPool2d, 3: nn.AdaptiveAvgPool3d}


class _ConvNet(nn.Module):
    def __init__(self, trajectory_shape: tuple[int, ...], cond_dim: int, channels: int, pooled: int) -> None:
        super().__init__()
        time, fields, *spatial = trajectory_shape
        dims = 1 + len(spatial)
        if dims not in CONV:
            raise ValueError(f"ConvClassifier: trajectory shape {trajectory_shape} has {dims} conv dimensions, expected 1-3")
        self.trajectory_shape, self.cond_dim = trajectory_shape, cond_dim
        conv = CONV[dims]
        self.encoder = nn.Sequential(
            conv(fields, channels, 3, stride=2, padding=1),
            nn.ELU(),
            conv(channels, 2 * channels, 3, stride=2, padding=1),
            nn.ELU(),
            POOL[dims](pooled),
            nn.Flatten(),
        )
        width = 64
        self.condition = nn.Sequential(nn.Linear(cond_dim, width), nn.ELU()) if cond_dim else None
        head_in = 2 * channels * pooled**dims + (width if cond_dim else 0)
        self.head = nn.Sequential(nn.Linear(head_in, width), nn.ELU(), nn.Linear(width, 1))

    def forward(self, rows: Tensor) -> Tensor:
        cond, trajectory = rows[:, : self.cond_dim], rows[:, self.cond_dim :]
        trajectory = trajectory.reshape(len(rows), *self.trajectory_shape)
        trajectory = trajectory.movedim(2, 1)  # (B, C, T, *spatial)
        features = [self.encoder(trajectory)]
        if self.condition is not None:
            features.append(self.condition(cond))
        return self.head(torch.cat(features, dim=1)).squeeze(1)


class ConvClassifier(ClassifierMixin, BaseEstimator):
    """Binary classifier (labels 0/1) trained with Adam and early stopping on a held-out fraction.

    Args:
        trajectory_shape: (T, C, *spatial) of the trajectory part of each row.
        cond_dim: number of leading conditioning features.
        channels: width of the first convolution (the second has twice as many).
        pooled: size per conv dimension after adaptive average pooling.
        max_epochs, batch_size, lr: training; patience: epochs without a better held-out
            loss before stopping (the best weights are kept).
        validation_fraction: share of the training rows held out for early stopping.
        random_state: seed of the initial weights, the split and the batch order.
        device: where to train ("cpu", "cuda", ...).
    """

    def __init__(
        self,
        trajectory_shape: tuple[int, ...] = (1, 1),
        cond_dim: int = 0,
        channels: int = 16,
        pooled: int = 4,
        max_epochs: int = 100,
        batch_size: int = 128,
        lr: float = 1e-3,
        patience: int = 5,
        validation_fraction: float = 0.1,
        random_state: int = 0,
        device: str = "cpu",
    ) -> None:
        self.trajectory_shape, self.cond_dim, self.channels, self.pooled = trajectory_shape, cond_dim, channels, pooled
        self.max_epochs, self.batch_size, self.lr, self.patience = max_epochs, batch_size, lr, patience
        self.validation_fraction, self.random_state, self.device = validation_fraction, random_state, device

    def fit(self, features: np.ndarray, labels: np.ndarray) -> ConvClassifier:
        """Train with early stopping; works inside Lightning's validation (under inference mode) too."""
        self.classes_ = np.unique(labels)
        if not np.array_equal(self.classes_, [0, 1]):
            raise ValueError(f"ConvClassifier: expected labels 0 and 1, got {self.classes_.tolist()}")
        with torch.inference_mode(False), torch.enable_grad():
            self.net_ = self._train(features, labels).eval()
        return self

    def _train(self, features: np.ndarray, labels: np.ndarray) -> nn.Module:
        g = torch.Generator().manual_seed(self.random_state)
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(self.random_state)
            net = _ConvNet(tuple(self.trajectory_shape), self.cond_dim, self.channels, self.pooled).to(self.device)
        x = torch.as_tensor(features, dtype=torch.float32, device=self.device)
        y = torch.as_tensor(labels, dtype=torch.float32, device=self.device)
        order = torch.randperm(len(x), generator=g).to(self.device)
        n_held = max(1, int(self.validation_fraction * len(x)))
        held, train = order[:n_held], order[n_held:]
        optimizer = torch.optim.Adam(net.parameters(), lr=self.lr)
        best_loss, best_state, waited = float("inf"), None, 0
        for _ in range(self.max_epochs):
            net.train()
            for batch in train[torch.randperm(len(train), generator=g).to(self.device)].split(self.batch_size):
                loss = nn.functional.binary_cross_entropy_with_logits(net(x[batch]), y[batch])
                optimizer.zero_grad(set_to_none=True)
                loss.backward()
                optimizer.step()
            held_loss = self._loss(net, x[held], y[held])
            if held_loss < best_loss:
                best_loss, waited = held_loss, 0
                best_state = {k: v.detach().clone() for k, v in net.state_dict().items()}
            else:
                waited += 1
                if waited >= self.patience:
                    break
        if best_state is None:
            raise ValueError("ConvClassifier: the held-out loss was never finite (NaN/Inf in the features?)")
        net.load_state_dict(best_state)
        return net

    @torch.no_grad()
    def _loss(self, net: nn.Module, x: Tensor, y: Tensor) -> float:
        net.eval()
        logits = torch.cat([net(chunk) for chunk in x.split(1024)])
        return float(nn.functional.binary_cross_entropy_with_logits(logits, y))

    @torch.no_grad()
    def decision_function(self, features: np.ndarray) -> np.ndarray:
        x = torch.as_tensor(features, dtype=torch.float32, device=self.device)
        return torch.cat([self.net_(chunk) for chunk in x.split(1024)]).cpu().numpy()

    def predict(self, features: np.ndarray) -> np.ndarray:
        return (self.decision_function(features) > 0).astype(np.int64)
