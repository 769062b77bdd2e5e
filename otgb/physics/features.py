"""Features of a state written in its variable names: the grammar of missing-effect terms.

A feature is a product of factors separated by ``*``; each factor is an atom, optionally
raised to an integer power with ``^``:

- ``1`` (the constant), a state name (``angle``, ``u``), a recorded input of a driven model (``drive``);
- on a field (a :class:`FieldModel`), a coordinate of its grid: ``s`` on a 1-D grid, ``x`` and ``y`` on a
  2-D one (``s^2`` on ``T`` is a source fixed in space), unless a state or parameter has that name;
- ``sin(x)``, ``cos(x)``, ``sign(x)``, ``|x|`` of a state name;
- spatial derivatives of a field's channel (a :class:`FieldModel`): ``d_s(u)`` and
  ``d_ss(u)`` on a 1-D grid, ``d_x(u)``, ``d_y(u)``, ``d_xx(u)``, ``d_yy(u)`` on a 2-D grid,
  and ``lap(u)``, the Laplacian, on any grid;
- a parametric form (:mod:`otgb.physics.forms`) of state names or coordinates with its parameters' values:
  ``rational(velocity; v0=0.8)``, ``bump(s; centre=0.3, width=0.1)``, ``my_package.Arrhenius(u; energy=2)``.

Examples: ``velocity*|velocity|`` (quadratic drag), ``u^3``, ``u*d_s(u)``, ``omega*velocity``
(a state times a physics parameter: names of ``theta_names`` are allowed too).
:func:`parse_feature` checks a feature against a model once; :func:`evaluate_feature`
computes it on states (B, *state_shape) -> (B, *grid_shape).
"""

from __future__ import annotations

import re
from dataclasses import dataclass

import torch
from torch import Tensor

from otgb.errors import InputError
from otgb.physics.forms import form_named

POINTWISE = {"sin": torch.sin, "cos": torch.cos, "sign": torch.sign}
SPATIAL_1D = {"d_s": (1, -1), "d_ss": (2, -1)}  # name -> (order, axis)
SPATIAL_2D = {"d_x": (1, -2), "d_y": (1, -1), "d_xx": (2, -2), "d_yy": (2, -1)}
_NAME = r"[A-Za-z_]\w*"
_FORM = re.compile(r"^(?P<form>[A-Za-z_][\w.]*)\((?P<args>[^;()]*);(?P<values>[^;()]*)\)$")
_ATOM = re.compile(rf"^(?:(?P<func>[a-z_]+)\((?P<arg>{_NAME})\)|\|(?P<abs>{_NAME})\||(?P<name>{_NAME})|(?P<one>1))$")


@dataclass(frozen=True)
class Factor:
    """One factor of a feature: ``op`` applied to the variable ``name``, raised to ``power``.

    ``op`` is "one" (the constant), "var", "abs", a pointwise function, a spatial operator or "form" (``name``
    the form's, ``args`` its variables, ``values`` its parameters' values in the form's order).
    """

    op: str
    name: str
    power: int = 1
    args: tuple[str, ...] = ()
    values: tuple[float, ...] = ()


def parse_feature(feature: str, model: object) -> tuple[Factor, ...]:
    """The factors of ``feature``, checked against ``model``'s names and grid; InputError if invalid."""
    if not isinstance(feature, str) or not feature.strip():
        raise InputError(f"feature {feature!r} is invalid; expected e.g. 'velocity*|velocity|' or 'lap(u)'")
    factors = tuple(_parse_factor(part.strip(), feature, model) for part in feature.replace(" ", "").split("*"))
    return tuple(f for f in factors if f.op != "one") or factors[:1]


def _parse_factor(text: str, feature: str, model: object) -> Factor:
    base, _, power = text.partition("^")
    if power and not (power.isdigit() and int(power) >= 1):
        raise InputError(f"feature {feature!r}: power {power!r} in {text!r} is invalid; expected a whole number >= 1")
    match = _ATOM.match(base)
    if match is None and _FORM.match(base) is None:
        raise InputError(f"feature {feature!r}: cannot read {text!r}; {_grammar_hint(model)}")
    power = int(power or 1)
    form = _FORM.match(base)
    if form is not None:
        return _form_factor(form, power, feature, model)
    if match["one"]:
        return Factor("one", "", 1)
    if match["abs"]:
        return Factor("abs", _checked_name(match["abs"], feature, model), power)
    if match["name"]:
        return Factor("var", _checked_name(match["name"], feature, model), power)
    func, name = match["func"], _checked_name(match["arg"], feature, model, states_only=True)
    if func not in POINTWISE and func not in _spatial_ops(model) and not (func == "lap" and _spatial_ops(model)):
        raise InputError(f"feature {feature!r}: unknown function {func!r}; {_grammar_hint(model)}")
    return Factor(func, name, power)


def _form_factor(match: re.Match, power: int, feature: str, model: object) -> Factor:
    form = form_named(match["form"])
    args = tuple(_checked_name(a, feature, model) for a in match["args"].split(","))
    written = dict(item.partition("=")[::2] for item in match["values"].split(",") if item)
    if len(args) != form.arity or tuple(written) != tuple(form.parameters):
        raise InputError(
            f"feature {feature!r}: the form {match['form']!r} takes {form.arity} variable(s) and the parameters "
            f"{list(form.parameters)} written name=value in that order; got {list(args)} and {list(written)}"
        )
    try:
        values = tuple(float(v) for v in written.values())
    except ValueError:
        raise InputError(f"feature {feature!r}: the parameters of {match['form']!r} must be numbers; got {written}") from None
    return Factor("form", match["form"], power, args, values)


def form_factor(feature: str) -> Factor | None:
    """The form of a feature that is one parametric form (``rational(velocity;v0=0.8)``), its names unchecked;
    None for any other feature."""
    match = _FORM.match(feature.replace(" ", ""))
    if match is None:
        return None
    values = tuple(float(item.partition("=")[2]) for item in match["values"].split(",") if item)
    return Factor("form", match["form"], 1, tuple(match["args"].split(",")), values)


def _checked_name(name: str, feature: str, model: object, states_only: bool = False) -> str:
    names = (*model.state_names, *getattr(model, "input_names", ()))
    names += () if states_only else (*model.theta_names, *_coordinate_names(model))
    if name not in names:
        raise InputError(f"feature {feature!r}: {name!r} is not a name of {type(model).__name__}; expected one of {names}")
    return name


def _coordinate_names(model: object) -> tuple[str, ...]:
    return tuple(getattr(model, "coordinate_names", ()))


def _spatial_ops(model: object) -> dict[str, tuple[int, int]]:
    dims = getattr(model, "spatial_dims", 0)
    return SPATIAL_1D if dims == 1 else SPATIAL_2D if dims == 2 else {}


def _grammar_hint(model: object) -> str:
    spatial = ", ".join(f"{op}(u)" for op in [*_spatial_ops(model), "lap"]) if getattr(model, "spatial_dims", 0) else "none"
    return (
        f"expected factors joined by '*' among 1, a name of "
        f"{(*model.state_names, *getattr(model, 'input_names', ()), *model.theta_names, *_coordinate_names(model))}, "
        f"sin(x), cos(x), sign(x), |x|, each optionally '^k'; spatial operators: {spatial}"
    )


def evaluate_feature(
    factors: tuple[Factor, ...],
    state: Tensor,
    theta: Tensor,
    model: object,
    powers: dict[tuple, Tensor] | None = None,
    inputs: Tensor | None = None,
) -> Tensor:
    """The feature on states (B, *state_shape) with parameters theta (B, P) and a driven model's input values ``inputs``
    (B, I; None: zero): shape (B, *grid_shape).

    ``powers``: the factors' values already computed on this state and theta (filled in here), so that
    features evaluated together (an augmented model's terms) compute each ``u^2`` or ``lap(v)`` once.
    """
    powers = {} if powers is None else powers
    value = None
    for factor in factors:
        if factor.op == "one":
            return torch.ones_like(state[:, 0])
        if factor not in powers:
            powers[factor] = _atom(factor, state, theta, model, inputs) ** factor.power
        value = powers[factor] if value is None else value * powers[factor]
    return value


def variable_values(name: str, state: Tensor, theta: Tensor | None, model: object, inputs: Tensor | None = None) -> Tensor:
    """A state component, a recorded input (its value ``inputs`` (B, I), zero where None), a grid coordinate or a
    physics parameter of ``model`` as (B, *grid)."""
    if name in model.state_names:
        return state[:, model.state_names.index(name)]
    if name in getattr(model, "input_names", ()):
        if inputs is None:
            return torch.zeros_like(state[:, 0])
        value = inputs[:, model.input_names.index(name)].to(state.dtype)
        return value.reshape(-1, *([1] * (state.dim() - 2))).expand_as(state[:, 0])
    if name in _coordinate_names(model):
        return model.coordinate(name, state.device, state.dtype).expand_as(state[:, 0])
    return theta[:, model.theta_names.index(name)].reshape(-1, *([1] * (state.dim() - 2))).expand_as(state[:, 0])


def _atom(factor: Factor, state: Tensor, theta: Tensor, model: object, inputs: Tensor | None) -> Tensor:
    if factor.op == "form":
        arguments = [variable_values(name, state, theta, model, inputs) for name in factor.args]
        values = [torch.tensor(v, dtype=state.dtype, device=state.device) for v in factor.values]
        return form_named(factor.name).shape(arguments, values)
    u = variable_values(factor.name, state, theta, model, inputs)
    if factor.op == "var":
        return u
    if factor.op == "abs":
        return u.abs()
    if factor.op in POINTWISE:
        return POINTWISE[factor.op](u)
    if factor.op == "lap":
        return model.laplacian(u)
    order, axis = _spatial_ops(model)[factor.op]
    return model.derivative(u, axis) if order == 1 else model.second_derivative(u, axis)


def is_local(feature: str, model: object) -> bool:
    """Whether ``feature`` depends on the state at one point only (no spatial derivative in it)."""
    spatial = {*_spatial_ops(model), "lap"}
    return all(factor.op not in spatial for factor in parse_feature(feature, model))
