"""f_p augmented with named library terms whose coefficients are new physics parameters.

What ``otgb discover`` writes into ``augmented.yaml``:

    data:
      physics:
        class_path: otgb.physics.Augmented
        init_args:
          base: {class_path: otgb.physics.Pendulum}
          terms:
            - class_path: otgb.physics.LibraryTerm
              init_args: {feature: velocity, component: velocity,
                          coefficient: {class_path: otgb.physics.Constant, init_args: {value: -1.2}}}

The augmented model is f_p's system with theta extended by one parameter per term (named by
the term, drawn from the term's coefficient prior), so the data module, the grey-box map and
the evaluation take it as any other f_p: a second round of training or discovery starts from
the improved physics.
"""

from __future__ import annotations

import copy
from collections.abc import Sequence
from contextlib import AbstractContextManager

import torch
from torch import Tensor, nn

from otgb.errors import InputError
from otgb.physics.base import PhysicsModel
from otgb.physics.priors import Prior, sample_joint
from otgb.physics.terms import FormTerm, LibraryTerm

ADDED_TERMS = (LibraryTerm, FormTerm)  # the kinds of term an augmented model adds


class Augmented(PhysicsModel):
    """``base`` plus ``terms``: d(state)/dt = f_base(state, theta) + sum_k c_k feature_k(state).

    theta is (base theta, each term's columns: a library term's coefficient c_k, a form's coefficient and
    parameters); ``theta_names`` appends the terms' ``parameter_names``. Everything
    else (states, observation, grid, initial states, time grid, solver, the correction's slot)
    is the base model's.

    Args:
        base: the physics model f_p that is augmented (with no hidden effect of its own).
        terms: the named terms added to it, each a :class:`otgb.physics.LibraryTerm` or :class:`otgb.physics.FormTerm`.
    """

    state_names = None  # per instance: the base model's

    def __init__(self, base: PhysicsModel, terms: Sequence[LibraryTerm]) -> None:
        if not isinstance(base, PhysicsModel) or len(base.terms) > 0:
            raise InputError(f"Augmented: base={base!r} is invalid; expected a physics model without hidden-effect terms")
        if isinstance(terms, (str, *ADDED_TERMS)) or not all(isinstance(t, ADDED_TERMS) for t in terms):
            raise InputError(
                f"Augmented: terms={terms!r} is invalid; expected a list of otgb.physics.LibraryTerm or otgb.physics.FormTerm"
            )
        names = [name for term in terms for name in term.parameter_names]
        taken = {*base.theta_names, *base.state_names, *getattr(base, "coordinate_names", ())}
        clash = sorted({n for n in names if names.count(n) > 1} | (set(names) & taken))
        if clash:
            raise InputError(
                f"Augmented: the term names {clash} repeat a name of the base model (a state, parameter or grid "
                "coordinate) or of another term"
            )
        for attr in ("state_names", "observed", "input_names", "angle_names", "velocity_names", "units"):
            object.__setattr__(self, attr, getattr(base, attr))
        object.__setattr__(self, "theta_names", (*base.theta_names, *names))
        super().__init__(base.dt, base.n_obs, base.include_initial, base.step_size, base.method)
        self._read_times = base._read_times
        self.base = base
        self.added = nn.ModuleList(terms)
        for term in terms:
            term.check_model(base)

    def __getattr__(self, name: str) -> object:
        """Attributes the base model has and this one lacks (its grid, stencils, ...)."""
        try:
            return super().__getattr__(name)
        except AttributeError:
            base = self.__dict__.get("_modules", {}).get("base")
            if base is None:
                raise
            return getattr(base, name)

    @property
    def state_shape(self) -> tuple[int, ...]:
        return self.base.state_shape

    @property
    def correction_shape(self) -> tuple[int, ...]:
        return self.base.correction_shape

    @property
    def priors(self) -> dict[str, Prior]:
        added = {name: prior for term in self.added for name, prior in zip(term.parameter_names, term.priors.values())}
        return {**self.base.priors, **added}

    def with_priors(self, priors: dict[str, Prior]) -> Augmented:
        """The base model's priors replaced (:meth:`PhysicsModel.with_priors`), the same terms added."""
        return Augmented(self.base.with_priors(priors), copy.deepcopy(list(self.added)))

    def add_correction(self, dstate: Tensor, correction: Tensor) -> Tensor:
        return self.base.add_correction(dstate, correction)

    def observe(self, state: Tensor) -> Tensor:
        return self.base.observe(state)

    def rows_from(self, first: int) -> AbstractContextManager[None]:
        return self.base.rows_from(first)

    @property
    def is_driven(self) -> bool:
        return self.base.is_driven

    def signal_times(self) -> Tensor:
        return self.base.signal_times()

    def sample_signals(self, n: int, generator: torch.Generator) -> Tensor | None:
        return self.base.sample_signals(n, generator)

    def driven_by(self, recorded: object) -> Augmented:
        """The base model driven by ``recorded`` (:meth:`PhysicsModel.driven_by`), the same terms added."""
        model = Augmented(self.base.driven_by(recorded), copy.deepcopy(list(self.added)))
        model._read_times = self._read_times
        return model

    def field(self, state: Tensor, theta: Tensor, inputs: Tensor | None = None) -> Tensor:
        base_theta = theta[:, : self.base.theta_dim]
        dstate = self.base.known_field(state, base_theta, inputs)
        if not len(self.added):
            return dstate
        rates, powers = list(dstate.unbind(1)), {}  # per component; each factor's value computed once
        column = self.base.theta_dim
        for term in self.added:
            index, width = self.base.state_names.index(term.component), term.n_params
            rate = term.rate(state, theta[:, column : column + width], self.base, base_theta, powers, inputs)
            rates[index] = rates[index] + rate
            column += width
        return torch.stack(rates, dim=1)

    def sample_theta(self, n: int, generator: torch.Generator) -> Tensor:
        """The base model's theta, then one joint draw of the terms' priors (:func:`otgb.physics.priors.sample_joint`)."""
        coefficients = sample_joint([prior for term in self.added for prior in term.priors.values()], n, generator)
        return torch.cat([self.base.sample_theta(n, generator), coefficients], dim=1)

    def sample_initial_state(self, n: int, generator: torch.Generator) -> Tensor:
        return self.base.sample_initial_state(n, generator)
