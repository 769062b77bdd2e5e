"""Every random stream of a discovery run, derived from its one seed (``discover.seed``) in this module.

A step of the pipeline takes its streams from :class:`Seeds` (held by the run's
:class:`~otgb.discovery.settings.Context`); the primitives it calls (a permutation test, a bootstrap, a fit) take the
integer seed of their stream, and the few that draw a second stream beside it offset it by the constants below. So
changing how a stream is derived is a change to this file alone, and two runs of the same config and seed draw the
same numbers.

Streams told apart by name (:meth:`Seeds.simulation`, :meth:`Seeds.rows`) are hashed with the run's seed
(:func:`otgb.data.seeding.derive_seed`): two simulations of different names never share their inputs, and f_p
simulated under the grey-box's name (:data:`otgb.discovery.draws.GREYBOX`) gets the grey-box's inputs on purpose.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from otgb.data.seeding import generator_for

MEASUREMENT_NOISE = 7919  # the noise that simulations compared with the measurements carry
UNDERTRAINED_DRAWS = 100  # + the repeat: the grey-box's and f_p's draws of the undertrained check

# Second streams of the primitives, offset from the seed they are given:
FIT_INPUTS, FIT_NOISE = 1, 2  # a discrepancy score's inputs (x0, theta) and its coefficients' noise (scores)
SLOPE_BOOTSTRAP = 1  # the bootstrap of f_phi's slopes on the kept terms (regression.describe_terms)
FITTED_CORRECTION = 5  # the dense fit's trajectories whose correction the library search regresses (search)


def stream(seed: int, offset: int = 0) -> torch.Generator:
    """A CPU generator of the stream ``offset`` beside ``seed``."""
    return torch.Generator().manual_seed(seed + offset)


@dataclass(frozen=True)
class Seeds:
    """The streams of one discovery run, all from ``root`` (``discover.seed``).

    The permutation tests, the bootstraps, the coefficient fits, the C2ST's folds, the Reference's halves, the
    pointwise errors and the component analysis each take ``root`` itself: each is a different function of it, so
    none repeats another's draws.
    """

    root: int

    def simulation(self, name: str) -> torch.Generator:
        """The inputs (x0, theta) of the simulation called ``name`` (``gap-f_p``, ``closer-augmented``, ...)."""
        return generator_for(self.root, "discover", name)

    def rows(self, n: int) -> torch.Generator:
        """The permutation that picks a subset of ``n`` measured rows: one per number of rows, so the before and after
        maps of a part see the same trajectories."""
        return generator_for(self.root, "discover", "rows", n)

    @property
    def measurement_noise(self) -> int:
        """The seed of the noise added to simulations compared with the measurements."""
        return self.root + MEASUREMENT_NOISE

    def undertrained_draw(self, repeat: int) -> Seeds:
        """The streams of the ``repeat``-th draw of the grey-box and of f_p in the undertrained check."""
        return Seeds(self.root + UNDERTRAINED_DRAWS + repeat)
