"""The settings of a discovery run (the ``discover:`` section of ``otgb discover``'s config) and the measured
trajectories it works on, split into training, validation and test parts."""

from __future__ import annotations

from contextlib import AbstractContextManager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from otgb.discovery.families import FAMILIES
from otgb.discovery.fit_cache import FitCache
from otgb.discovery.library import MAX_DEGREE
from otgb.discovery.refine import SPREAD_SAMPLES
from otgb.discovery.seeds import Seeds
from otgb.errors import InputError
from otgb.physics.base import PhysicsModel
from otgb.physics.forms import form_named

MAX_FOLDS = 20  # each fold costs a refit of every model compared


@dataclass(frozen=True)
class PermutationSettings:
    """The permutation tests' settings: the disagreement maps and the test of which model is nearer."""

    n_permutations: int
    alpha: float
    regions_per_axis: int
    locate_rows: int


@dataclass(frozen=True)
class LibrarySettings:
    """How f_phi is named: its draws, the bootstrap, the candidate library and the candidates cross-checked."""

    n_trajectories: int
    n_bootstrap: int
    theta_products: bool
    position_degree: int
    strong_candidates: int


@dataclass(frozen=True)
class FitSettings:
    """How coefficients, their prior families and f_p's recalibrated priors are fitted and scored."""

    steps: int
    batch: int
    score_rows: int
    families: tuple[str, ...]
    spread_samples: int
    recalibrate: bool
    forms: tuple[dict, ...] = ()  # declared parametric forms (:func:`declared_forms`)
    folds: int = 1  # folds the held-out scores are cross-fitted over (:mod:`otgb.discovery.crossfit`); 1: the validation part


class DiscoverySettings:
    """Settings of ``otgb discover`` (the ``discover:`` section of its config), validated once and frozen, in groups:
    ``tests`` (:class:`PermutationSettings`), ``library`` (:class:`LibrarySettings`), ``fits`` (:class:`FitSettings`), and
    the gap table's judge, the seed and the fit cache.

    Args:
        n_permutations: Label permutations per p-value of the disagreement map and of the test of which model is nearer.
        alpha: False discovery rate of the disagreement map (Benjamini-Hochberg), and the level of the paired check and of
            the test of whether the augmented physics is nearer to the test part than f_p alone.
        regions_per_axis: Blocks per spatial axis in which a field's cells are compared.
        locate_rows: Most measured trajectories in a disagreement map (a random subset beyond, drawn with ``seed``),
            and as many simulated: the permutation tests' time and memory grow with the square of the rows.
        score_rows: Most measured trajectories of the training and validation parts that the coefficient fits and the
            scores of fits, prior families and spreads use (a random subset beyond): each score grows with the square.
        n_trajectories: Generated trajectories along which the correction f_phi is evaluated.
        n_bootstrap: Bootstrap resamples (of f_phi's trajectories) for inclusion probabilities and f_phi's slope intervals.
        theta_products: Whether the library also offers each feature times each physics parameter.
        position_degree: On a field, the library also offers the grid's coordinates (``s``; ``x``, ``y``) and their
            products and powers up to this degree, as terms fixed in space (a heater, a sink); 0: none.
        strong_candidates: Candidates per component cross-checked alone (besides the selected ones), by univariate R^2.
        fit_steps: L-BFGS iterations of each distribution-matching fit of coefficients.
        fit_batch: Simulated (and at most as many measured) trajectories of each distribution-matching fit; its
            memory stays bounded at any size (the gradient is taken a chunk of trajectories at a time).
        families: Prior families tried for the coefficients, simplest first.
        spread_samples: Independent simulated samples (of ``fit_batch`` trajectories each) whose mean discrepancy a fit
            of a family that varies, and of f_p's recalibrated priors, minimises: a spread changes the discrepancy by
            less than one sample's noise. Each such fit costs this many times a constant's.
        recalibrate: Whether f_p's parameters' priors are also refitted and weighed against f_p alone and the named
            terms (:mod:`otgb.discovery.recalibration`).
        folds: Folds of the measured training and validation trajectories over which every held-out score that decides
            between models is cross-fitted (:mod:`otgb.discovery.crossfit`): each model refitted on K - 1 folds and scored
            on the one left out, so that each decision sees every one of those trajectories out of sample; 1: fitted on
            the training part and scored on the validation part alone. The test part is never among them.
        forms: Parametric forms of your own, weighed like the built-in ones (:mod:`otgb.discovery.forms`), each
            ``{class_path: a subclass of otgb.physics.forms.Form (or a built-in form's name), component: the state
            whose rate it adds to, variables: [what it is a function of], ranges: {parameter: [low, high]}}``.
        c2st_classifier: The C2ST judge of the gap table ("auto", "mlp" or "conv").
        seed: Seed of every draw of the workflow.
        fit_cache: A folder where each finished coefficient fit is stored and from which a run that asks for the same
            fit reads it (:mod:`otgb.discovery.fit_cache`): a stopped run started again with the same folder resumes.
            ``auto``: ``fit_cache`` beside the run directories (``runs/<config stem>/fit_cache``) under ``otgb discover``
            and ``MissingEffect.fit`` (inside its ``run_dir``; without one, a temporary folder), none where the workflow
            is called directly; ``null``: no fit is stored.
    """

    def __init__(
        self,
        n_permutations: int = 999,
        alpha: float = 0.05,
        regions_per_axis: int = 4,
        locate_rows: int = 1000,
        score_rows: int = 2000,
        n_trajectories: int = 256,
        n_bootstrap: int = 30,
        theta_products: bool = False,
        position_degree: int = 0,
        strong_candidates: int = 3,
        fit_steps: int = 50,
        fit_batch: int = 1024,
        families: tuple[str, ...] = FAMILIES,
        spread_samples: int = SPREAD_SAMPLES,
        recalibrate: bool = True,
        forms: list[dict] | None = None,
        folds: int = 1,
        c2st_classifier: str = "auto",
        seed: int = 0,
        fit_cache: str | None = "auto",
    ) -> None:
        if n_permutations < 19 or not 0 < alpha < 1 or regions_per_axis < 1 or min(locate_rows, score_rows) < 10:
            raise InputError(
                f"discover: need n_permutations >= 19, 0 < alpha < 1, regions_per_axis >= 1, locate_rows >= 10, "
                f"score_rows >= 10; got {n_permutations}, {alpha}, {regions_per_axis}, {locate_rows}, {score_rows}"
            )
        if n_trajectories < 10 or n_bootstrap < 1 or fit_steps < 1 or fit_batch < 2 or strong_candidates < 0:
            raise InputError(
                "discover: need n_trajectories >= 10, n_bootstrap >= 1, fit_steps >= 1, fit_batch >= 2, strong_candidates >= 0"
            )
        if isinstance(spread_samples, bool) or not (isinstance(spread_samples, int) and spread_samples >= 1):
            raise InputError(f"discover.spread_samples={spread_samples!r} is invalid; expected a whole number >= 1")
        if isinstance(folds, bool) or not (isinstance(folds, int) and 1 <= folds <= MAX_FOLDS):
            raise InputError(f"discover.folds={folds!r} is invalid; expected a whole number 1..{MAX_FOLDS} (1: no cross-fitting)")
        if isinstance(position_degree, bool) or not (isinstance(position_degree, int) and 0 <= position_degree <= MAX_DEGREE):
            raise InputError(f"discover.position_degree={position_degree!r} is invalid; expected a whole number 0..{MAX_DEGREE}")
        unknown = [f for f in families if f not in FAMILIES]
        if unknown or not families:
            raise InputError(f"discover.families={list(families)}: expected a non-empty list among {list(FAMILIES)}")
        self.tests = PermutationSettings(n_permutations, alpha, regions_per_axis, locate_rows)
        self.library = LibrarySettings(n_trajectories, n_bootstrap, bool(theta_products), position_degree, strong_candidates)
        fits = (
            fit_steps,
            fit_batch,
            score_rows,
            tuple(families),
            spread_samples,
            bool(recalibrate),
            declared_forms(forms),
            folds,
        )
        self.fits = FitSettings(*fits)
        self.c2st_classifier, self.seed, self.fit_cache = c2st_classifier, seed, fit_cache
        self.cache = None if fit_cache in (None, "auto") else FitCache(fit_cache)  # refuses a file before any work
        self._frozen = True

    def __setattr__(self, name: str, value: Any) -> None:
        if getattr(self, "_frozen", False):
            raise AttributeError(f"DiscoverySettings are frozen once validated: {name} cannot be set")
        super().__setattr__(name, value)


def declared_forms(forms: list[dict] | None) -> tuple[dict, ...]:
    """``discover.forms`` checked: each entry's keys, its form (importable), variables and a range per parameter."""
    checked = []
    for i, entry in enumerate(forms or []):
        where = f"discover.forms[{i}]"
        keys = {"class_path", "component", "variables", "ranges"}
        if not isinstance(entry, dict) or set(entry) != keys:
            got = sorted(entry) if isinstance(entry, dict) else entry
            raise InputError(f"{where}={got!r} is invalid; expected the keys {sorted(keys)}")
        form = form_named(entry["class_path"])
        variables = [entry["variables"]] if isinstance(entry["variables"], str) else list(entry["variables"])
        ranges = entry["ranges"] if isinstance(entry["ranges"], dict) else {}
        bad = [k for k in form.parameters if not _is_range(ranges.get(k), k in form.positive)]
        if bad or set(ranges) != set(form.parameters) or len(variables) != form.arity:
            raise InputError(
                f"{where}: {entry['class_path']} takes {form.arity} variable(s) and a range [low, high] (low < high; "
                f"low > 0 for {list(form.positive)}) for each of {list(form.parameters)}; got variables={variables}, "
                f"ranges={entry['ranges']!r}"
            )
        checked.append({**entry, "variables": variables, "ranges": {k: tuple(map(float, ranges[k])) for k in form.parameters}})
    return tuple(checked)


def _is_range(value: Any, positive: bool) -> bool:
    if not (isinstance(value, (list, tuple)) and len(value) == 2 and all(isinstance(v, (int, float)) for v in value)):
        return False
    return value[0] < value[1] and (value[0] > 0 or not positive)


@dataclass(frozen=True)
class Context:
    """Where a discovery run computes, what it keeps and what it draws, beside its settings: the device of the
    coefficient fits (a CUDA device where the grey-box trains on one, else the CPU: Apple's MPS has no float64 for
    scores), the fit cache (:mod:`otgb.discovery.fit_cache`; None: no fit is stored) and the run's random streams
    (:class:`~otgb.discovery.seeds.Seeds`), the measurement noise of its simulations among them."""

    device: torch.device = torch.device("cpu")
    cache: FitCache | None = None
    seeds: Seeds = Seeds(0)

    @classmethod
    def of(cls, settings: DiscoverySettings, runs: Path | None = None, device: torch.device | None = None) -> Context:
        """The context of ``settings``: ``fit_cache: auto`` resolved to ``runs/fit_cache`` where ``runs`` (the folder of
        the run directories) is given, none otherwise; the fits on ``device`` if it is a CUDA device; the streams of
        ``settings.seed``."""
        cache = FitCache(runs / "fit_cache") if settings.fit_cache == "auto" and runs is not None else settings.cache
        on_cuda = device is not None and device.type == "cuda"
        return cls(device if on_cuda else torch.device("cpu"), cache, Seeds(settings.seed))

    def as_measured(self, physics: PhysicsModel, noise: float) -> AbstractContextManager[None]:
        """Within it, simulations of ``physics`` compared with the measurements carry the measurements' noise of sd
        ``noise`` (the truth does not), from the run's stream of it."""
        return physics.measured_with_noise(noise, self.seeds.measurement_noise)


@dataclass(frozen=True)
class Measurements:
    """The measured trajectories (n, T, *obs) of each part of the split, the training and test parts' x0 and theta
    where the measurements recorded both, the sd of their noise (0: noise-free or not given) and the training and
    test parts' recorded input signals (None: none recorded)."""

    train: Tensor
    val: Tensor
    test: Tensor
    train_inputs: tuple[Tensor, Tensor] | None = None
    test_inputs: tuple[Tensor, Tensor] | None = None
    noise: float = 0.0
    train_signals: Tensor | None = None
    test_signals: Tensor | None = None

    @classmethod
    def from_datamodule(cls, datamodule: Any) -> Measurements:
        datamodule.setup("fit")
        datamodule.setup("test")
        val, test = datamodule.val_set["y"].flatten(0, 1), datamodule.test_set["y"].flatten(0, 1)
        train_inputs = datamodule.source.training_inputs()
        test_inputs = None if train_inputs is None else (datamodule.test_set["x0"], datamodule.test_set["theta"])
        signals = datamodule.source.training_signals(), datamodule.test_set.get("signals")
        return cls(datamodule.measured, val, test, train_inputs, test_inputs, datamodule.measurement_noise, *signals)

    def pairable(self) -> bool:
        """Whether the paired check (:mod:`otgb.discovery.paired`) applies: inputs recorded and the noise given."""
        return self.train_inputs is not None and self.noise > 0
