"""Parametric forms: shapes of an effect that are nonlinear in their own parameters.

A linear library term is ``c * feature(state)``; a form is ``c * shape(variables; parameters)``, whose
parameters (a friction's saturation speed, a power, a bump's centre and width) change its shape, not only its
size. The built-in forms, each of one variable u (the shape's slope or level at small u is 1, so c keeps the
meaning of the linear term it generalises):

- ``saturating``: ``v0 * tanh(u / v0)``, a friction that grows as ``c u`` at small speeds and saturates at ``c v0``;
- ``rational``: ``u / (1 + (u / v0)^2)``, a friction that peaks at the speed ``v0`` and falls off beyond it;
- ``stribeck``: ``sign(u) * (1 + ratio * exp(-(u / vs)^2))``, Coulomb friction ``c`` with a static excess of
  ``ratio`` at rest that fades over the Stribeck speed ``vs``;
- ``power``: ``sign(u) * |u|^p``, a power-law friction (p = 1 viscous, p = 2 quadratic drag);
- ``exponential``: ``exp(rate * u)``, an exponential dependence on a state (an Arrhenius-like rate);
- ``bump``: ``exp(-(s - centre)^2 / (2 width^2))`` of a grid coordinate s, a source fixed in space, and ``bump2``:
  ``exp(-((x - centre_x)^2 + (y - centre_y)^2) / (2 width^2))`` on a 2-D grid.

A form is used two ways: as a factor of a feature with its parameters' values written in
(``rational(velocity; v0=0.8)``, :mod:`otgb.physics.features`), a library term like any other; and as a
:class:`otgb.physics.FormTerm`, whose parameters are physics parameters drawn from priors (a DGP's hidden effect, or a fit
that moves them). A user's own form is a subclass of :class:`Form`, named by its class path in either.
"""

from __future__ import annotations

import importlib
from functools import cache
from typing import ClassVar

import torch
from torch import Tensor

from otgb.errors import InputError

Range = tuple[float, float]


class Form:
    """A shape ``shape(inputs, values)`` of ``arity`` variables with named parameters.

    Subclasses set ``parameters`` (names, in order), ``positive`` (those that are > 0, fitted on a log scale),
    ``kind`` ("friction" for a friction of its own velocity, whose physical sign is checked) and
    ``library_values`` (values of a parameter at which the form is a library term: a power law's p = 1), and implement
    :meth:`shape`; the built-ins also give :meth:`ranges` (where a search looks for the parameters, from the
    variables' sizes) and :meth:`label` (the effect's physical name).
    """

    name: ClassVar[str] = ""
    parameters: ClassVar[tuple[str, ...]] = ()
    positive: ClassVar[tuple[str, ...]] = ()
    arity: ClassVar[int] = 1
    kind: ClassVar[str | None] = None
    library_values: ClassVar[dict[str, tuple[float, ...]]] = {}  # parameter values at which it is a library term

    def shape(self, inputs: list[Tensor], values: list[Tensor]) -> Tensor:
        """The shape at the variables ``inputs`` (each (B, *grid)) for parameter ``values`` (each broadcastable)."""
        raise NotImplementedError

    def ranges(self, sizes: list[float], spans: list[Range]) -> dict[str, Range]:
        """Where each parameter is looked for, given each variable's largest size and its span (low, high)."""
        raise InputError(f"form {self.name or type(self).__name__}: give its parameters' ranges (discover.forms)")

    def label(self, coefficient: float) -> str:
        return f"{self.name or type(self).__name__} form"


def _friction(coefficient: float, what: str) -> str:
    return what if coefficient < 0 else f"{what} with the wrong sign (it pushes along the motion)"


class TanhSaturation(Form):
    name, parameters, positive, kind = "saturating", ("v0",), ("v0",), "friction"

    def shape(self, inputs: list[Tensor], values: list[Tensor]) -> Tensor:
        v0 = values[0].abs()
        return v0 * torch.tanh(inputs[0] / v0)

    def ranges(self, sizes: list[float], spans: list[Range]) -> dict[str, Range]:
        return {"v0": (0.02 * sizes[0], 5 * sizes[0])}

    def label(self, coefficient: float) -> str:
        return _friction(coefficient, "saturating friction (tanh)")


class RationalSaturation(Form):
    name, parameters, positive, kind = "rational", ("v0",), ("v0",), "friction"

    def shape(self, inputs: list[Tensor], values: list[Tensor]) -> Tensor:
        return inputs[0] / (1 + (inputs[0] / values[0]) ** 2)

    def ranges(self, sizes: list[float], spans: list[Range]) -> dict[str, Range]:
        return {"v0": (0.02 * sizes[0], 5 * sizes[0])}

    def label(self, coefficient: float) -> str:
        return _friction(coefficient, "saturating friction v/(1+(v/v0)^2)")


class Stribeck(Form):
    name, parameters, positive, kind = "stribeck", ("ratio", "vs"), ("vs",), "friction"
    library_values = {"ratio": (0.0,)}  # Coulomb friction

    def shape(self, inputs: list[Tensor], values: list[Tensor]) -> Tensor:
        v = inputs[0]
        return torch.sign(v) * (1 + values[0] * torch.exp(-((v / values[1]) ** 2)))

    def ranges(self, sizes: list[float], spans: list[Range]) -> dict[str, Range]:
        return {"ratio": (-0.9, 5.0), "vs": (0.02 * sizes[0], 2 * sizes[0])}

    def label(self, coefficient: float) -> str:
        return _friction(coefficient, "Stribeck friction")


class PowerLaw(Form):
    name, parameters, positive, kind = "power", ("p",), ("p",), "friction"
    library_values = {"p": (1.0, 2.0, 3.0)}  # viscous friction, quadratic drag, cubic drag

    def shape(self, inputs: list[Tensor], values: list[Tensor]) -> Tensor:
        v = inputs[0]  # |v|^p through a floor, so that its derivative in p stays finite where v = 0
        return torch.sign(v) * v.abs().clamp_min(1e-30) ** values[0]

    def ranges(self, sizes: list[float], spans: list[Range]) -> dict[str, Range]:
        return {"p": (0.2, 4.0)}

    def label(self, coefficient: float) -> str:
        return _friction(coefficient, "power-law friction |v|^p")


class Exponential(Form):
    name, parameters = "exponential", ("rate",)

    def shape(self, inputs: list[Tensor], values: list[Tensor]) -> Tensor:
        return torch.exp(values[0] * inputs[0])

    def ranges(self, sizes: list[float], spans: list[Range]) -> dict[str, Range]:
        return {"rate": (-5 / sizes[0], 5 / sizes[0])}

    def label(self, coefficient: float) -> str:
        return "exponential dependence on a state"


class GaussianBump(Form):
    name, parameters, positive = "bump", ("centre", "width"), ("width",)

    def shape(self, inputs: list[Tensor], values: list[Tensor]) -> Tensor:
        return torch.exp(-((inputs[0] - values[0]) ** 2) / (2 * values[1] ** 2))

    def ranges(self, sizes: list[float], spans: list[Range]) -> dict[str, Range]:
        (low, high), = spans  # fmt: skip
        return {"centre": (low, high), "width": (0.02 * (high - low), 0.5 * (high - low))}

    def label(self, coefficient: float) -> str:
        return ("source" if coefficient > 0 else "sink") + " localised in space (a Gaussian bump)"


class GaussianBump2D(GaussianBump):
    name, parameters, arity = "bump2", ("centre_x", "centre_y", "width"), 2

    def shape(self, inputs: list[Tensor], values: list[Tensor]) -> Tensor:
        distance = (inputs[0] - values[0]) ** 2 + (inputs[1] - values[1]) ** 2
        return torch.exp(-distance / (2 * values[2] ** 2))

    def ranges(self, sizes: list[float], spans: list[Range]) -> dict[str, Range]:
        (x_low, x_high), (y_low, y_high) = spans
        span = min(x_high - x_low, y_high - y_low)
        return {"centre_x": (x_low, x_high), "centre_y": (y_low, y_high), "width": (0.02 * span, 0.5 * span)}


BUILT_IN = {
    form.name: form
    for form in (TanhSaturation, RationalSaturation, Stribeck, PowerLaw, Exponential, GaussianBump, GaussianBump2D)
}
FRICTION_FORMS = ("saturating", "rational", "stribeck", "power")  # tried in place of a velocity's own friction terms


@cache
def form_named(name: str) -> Form:
    """The form (one instance per name) of a built-in ``name`` or of a class path (``my_package.forms.Arrhenius``,
    a :class:`Form` subclass)."""
    if name in BUILT_IN:
        return BUILT_IN[name]()
    module, _, attribute = name.rpartition(".")
    try:
        found = getattr(importlib.import_module(module), attribute) if module else None
    except (ImportError, AttributeError):
        found = None
    if not (isinstance(found, type) and issubclass(found, Form)):
        raise InputError(
            f"form {name!r} is unknown; expected one of {sorted(BUILT_IN)} or the class path of an otgb.physics.forms.Form"
        )
    return found()


def form_feature(name: str, variables: list[str] | tuple[str, ...], values: dict[str, float]) -> str:
    """The feature of form ``name`` of ``variables`` with its parameters' ``values`` written in, e.g.
    ``rational(velocity;v0=0.8)`` (:mod:`otgb.physics.features` reads it)."""
    written = ",".join(f"{key}={float(value):.6g}" for key, value in values.items())
    return f"{name}({','.join(variables)};{written})"
