"""The candidate library: features built from what a physics model declares, with physical names.

From ``state_names``, ``angle_names``, ``velocity_names``, ``theta_names`` and, for a
:class:`otgb.physics.FieldModel`, its grid, the library offers for each component the
correction acts on:

- the constant ``1``; the states and their products and powers up to degree 3;
- ``sin`` and ``cos`` of angles; ``v*|v|`` and ``sign(v)`` of velocities;
- for fields: first spatial derivatives and the Laplacian of each channel, and the advective
  products ``w*d_s(u)``; optionally (``position_degree``) the grid's coordinates and their products
  and powers up to that degree (``s``, ``s^2``, ``x*y``), for a source or sink fixed in space;
- for a model driven by recorded inputs (:mod:`otgb.physics.signals`): each input, and each input
  times each state and each sin/cos of an angle (``drive``, ``drive*velocity``, ``drive*cos(angle)``),
  for an input that f_p mis-scales or that acts through the state;
- optionally (``theta_products``) each of those times each physics parameter, for an effect
  whose strength depends on theta.

Each candidate carries a physical name from :func:`physical_name`'s vocabulary, which falls
back to the expression itself. Features follow :mod:`otgb.physics.features`.
"""

from __future__ import annotations

from dataclasses import dataclass
from itertools import combinations_with_replacement

from otgb.physics.base import PhysicsModel
from otgb.physics.features import SPATIAL_1D, SPATIAL_2D, form_factor
from otgb.physics.forms import form_named

MAX_DEGREE = 3


@dataclass(frozen=True)
class Candidate:
    """``feature`` as a term of d(component)/dt."""

    feature: str
    component: str


def monomials(names: tuple[str, ...], degree: int = MAX_DEGREE) -> list[str]:
    """Products and powers of ``names`` up to ``degree``: ``u``, ``u^2``, ``u*v``, ``u^2*v``, ..."""
    features = []
    for d in range(1, degree + 1):
        for combo in combinations_with_replacement(names, d):
            features.append("*".join(f"{n}^{combo.count(n)}" if combo.count(n) > 1 else n for n in dict.fromkeys(combo)))
    return features


def spatial_features(model: PhysicsModel) -> list[str]:
    """First derivatives and the Laplacian of each channel, and the advective products."""
    dims = getattr(model, "spatial_dims", 0)
    if not dims:
        return []
    first = [op for op, (order, _) in (SPATIAL_1D if dims == 1 else SPATIAL_2D).items() if order == 1]
    derivatives = [f"{op}({u})" for u in model.state_names for op in first]
    laplacians = [f"lap({u})" for u in model.state_names]
    advective = [f"{w}*{d}" for w in model.state_names for d in derivatives]
    return derivatives + laplacians + advective


def feature_names(model: PhysicsModel, theta_products: bool = False, position_degree: int = 0) -> list[str]:
    """Every candidate feature of ``model`` (the same for each component)."""
    features = ["1", *monomials(tuple(model.state_names))]
    features += monomials(tuple(getattr(model, "coordinate_names", ())), position_degree)
    features += [f"{f}({a})" for a in model.angle_names for f in ("sin", "cos")]
    features += [f"{v}*|{v}|" for v in model.velocity_names] + [f"sign({v})" for v in model.velocity_names]
    features += spatial_features(model)
    features += input_features(model)
    if theta_products:
        features += scaled_by_theta(list(features), model.theta_names)
    return features


def input_features(model: PhysicsModel) -> list[str]:
    """A driven model's inputs, and each times each state and each sin/cos of an angle; none where it is not driven."""
    if not model.is_driven:
        return []
    angles = [f"{f}({a})" for a in model.angle_names for f in ("sin", "cos")]
    return [*model.input_names, *(f"{u}*{s}" for u in model.input_names for s in (*model.state_names, *angles))]


def scaled_by_theta(features: list[str], theta_names: list[str], powers: tuple[int, ...] = (1,)) -> list[str]:
    """Each of ``features`` times each physics parameter raised to each of ``powers`` (``omega*velocity``,
    ``omega^2*sin(angle)``; the constant feature ``1`` gives the parameter itself)."""
    scales = [name if power == 1 else f"{name}^{power}" for name in theta_names for power in powers]
    return [scale if f == "1" else f"{scale}*{f}" for scale in scales for f in features]


def build_library(
    model: PhysicsModel, components: list[str], theta_products: bool = False, position_degree: int = 0
) -> list[Candidate]:
    """The candidates for each component the correction acts on."""
    features = feature_names(model, theta_products, position_degree)
    return [Candidate(feature, component) for component in components for feature in features]


def physical_name(feature: str, component: str, coefficient: float, model: PhysicsModel) -> str:
    """A physical name for ``coefficient * feature`` in d(component)/dt, or the expression itself."""
    factors = feature.split("*")
    thetas = [f for f in factors if f in model.theta_names]
    if thetas and len(thetas) < len(factors):
        rest = "*".join(f for f in factors if f not in model.theta_names)
        return f"{physical_name(rest, component, coefficient, model)} scaled by {', '.join(thetas)}"
    name = _named(feature, component, coefficient, model)
    return name if name is not None else f"{coefficient:+.3g} * {feature} on d{component}/dt"


def implausible(feature: str, component: str, coefficient: float, model: PhysicsModel) -> str | None:
    """Why ``coefficient * feature`` in d(component)/dt contradicts what its name implies for a passive system, or None.

    A velocity's own friction terms (``v``, ``v*|v|``, ``v^3``, ``sign(v)``) with a positive coefficient feed energy
    into the motion (negative damping, anti-drag); a field's own diffusion with a negative coefficient
    sharpens every gradient (anti-diffusion, an ill-posed PDE). Either can be real (a driven system), so it
    is a flag for the reader, not a rejection.
    """
    kind = signed_kind(feature, component, model)
    if kind == "friction" and coefficient > 0:
        return "feeds energy into the motion (a friction with the wrong sign)"
    if kind == "diffusion" and coefficient < 0:
        return "sharpens every gradient (a diffusion with the wrong sign; the PDE is ill-posed)"
    return None


def signed_kind(feature: str, component: str, model: PhysicsModel) -> str | None:
    """``friction`` (a velocity's own ``v``, ``v*|v|``, ``v^3``, ``sign(v)``, or a friction form of it) or ``diffusion``
    (a field's own ``lap``, ``d_ss``): the terms whose physical sign :func:`implausible` checks; None for any other."""
    v, form = component, form_factor(feature)
    if form is not None:
        own = form.args == (component,) and component in model.velocity_names
        return "friction" if own and form_named(form.name).kind == "friction" else None
    if v in model.velocity_names and feature in (v, f"{v}*|{v}|", f"{v}^3", f"sign({v})"):
        return "friction"
    if getattr(model, "spatial_dims", 0) and feature in (f"lap({component})", f"d_ss({component})"):
        return "diffusion"
    return None


def _named(feature: str, own: str, coefficient: float, model: PhysicsModel) -> str | None:
    form = form_factor(feature)
    if form is not None:
        return form_named(form.name).label(coefficient)
    sign = "negative" if coefficient < 0 else "positive"
    is_velocity = own in model.velocity_names
    field = bool(getattr(model, "spatial_dims", 0))
    if feature == "1":
        return ("constant drain" if coefficient < 0 else "constant source") if field else "constant forcing"
    if feature in model.input_names:
        return f"{feature} acting on d{own}/dt beyond f_p's (a mis-scaled or missing input gain)"
    inputs = [f for f in feature.split("*") if f in model.input_names]
    if inputs and len(inputs) < len(feature.split("*")):
        rest = "*".join(f for f in feature.split("*") if f not in model.input_names)
        return f"{', '.join(inputs)} acting through {rest}"
    if fixed_in_space(feature, model):
        return "forcing fixed in space"
    if feature == own:
        if is_velocity:
            return "viscous friction" if coefficient < 0 else "negative damping (self-excitation)"
        return "linear decay" if coefficient < 0 else "linear growth"
    if feature == f"{own}*|{own}|" and is_velocity:
        return "quadratic drag" if coefficient < 0 else "quadratic anti-drag"
    if feature == f"sign({own})" and is_velocity:
        return "Coulomb friction" if coefficient < 0 else "constant-magnitude push along the motion"
    if feature == f"{own}^2" and is_velocity:  # the same sign whichever way it moves: no friction
        return f"one-sided quadratic push (towards {'negative' if coefficient < 0 else 'positive'} {own})"
    if feature == f"{own}^2":
        return "logistic saturation" if coefficient < 0 else "quadratic growth"
    if feature == f"{own}^3" and is_velocity:
        return "cubic drag" if coefficient < 0 else "cubic anti-drag"
    if feature == f"{own}^3":
        return "cubic reaction (saturation)" if coefficient < 0 else "cubic reaction (growth)"
    if feature.startswith(("sin(", "cos(")) and is_velocity:
        return f"{'restoring' if coefficient < 0 else 'destabilising'} torque {feature}"
    if feature in model.state_names:
        if is_velocity and feature in model.angle_names:
            return "linear restoring force (spring)" if coefficient < 0 else "linear destabilising force"
        return f"linear coupling to {feature} ({sign})"
    if field:
        return _field_name(feature, own, coefficient)
    if all(_base(f) in model.state_names for f in feature.split("*")) and len({_base(f) for f in feature.split("*")}) > 1:
        return f"coupling {feature}"
    return None


def fixed_in_space(feature: str, model: PhysicsModel) -> bool:
    """Whether ``feature`` is a product of the grid's coordinates alone (``s^2``, ``x*y``): a source fixed in space."""
    names = getattr(model, "coordinate_names", ())
    return bool(names) and all(_base(factor) in names for factor in feature.split("*"))


def _base(factor: str) -> str:
    return factor.split("^")[0]


def _field_name(feature: str, own: str, coefficient: float) -> str | None:
    if feature in (f"lap({own})", f"d_ss({own})"):
        return "diffusion" if coefficient > 0 else "anti-diffusion"
    for axis in ("s", "x", "y"):
        if feature == f"d_{axis}({own})":
            direction = "towards +" if coefficient < 0 else "towards -"
            return f"advection along {axis} ({direction}{axis})"
        if feature == f"{own}*d_{axis}({own})":
            return f"nonlinear (Burgers) advection along {axis}"
    if feature.startswith("lap(") or feature.startswith("d_"):
        return f"cross-diffusion {feature}"
    if "d_" in feature:
        return f"advection by another channel {feature}"
    return f"coupling {feature}"


def term_name(candidate: Candidate, coefficient: float, physics: PhysicsModel) -> str:
    return physical_name(candidate.feature, candidate.component, coefficient, physics)
