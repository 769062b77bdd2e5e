"""Discovery from Python: configure a :class:`MissingEffect`, ``fit`` it to measurements, read the result.

    from otgb.discovery import MissingEffect

    finder = MissingEffect.from_config("configs/pendulum.yaml", {"data.simulation_budget": 32000})
    result = finder.fit(measurements)        # a file, an array (N, T, *obs) or a run from otgb.runs.load_run
    result.print()                           # the verdict, the named terms, the gap
    result.terms[0].name, result.terms[0].interval, result.augmented_physics

``fit`` runs what ``otgb discover`` runs (:func:`otgb.discovery.pipeline.discover`) on those measurements alone
(marginal mode: a config's ``data.hidden_effect`` is ignored). It writes nothing in the working directory: without
``run_dir`` the grey-box's logs and the fit cache go to a temporary folder that is removed; ``result.write(folder)``
writes the report's files where you choose.
"""

from __future__ import annotations

import inspect
import os
import tempfile
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
import yaml

from otgb.data.sources import FileMeasurements
from otgb.discovery.pipeline import discover
from otgb.discovery.result import DiscoveryResult
from otgb.discovery.session import build
from otgb.discovery.settings import DiscoverySettings
from otgb.errors import InputError
from otgb.parser_errors import closest
from otgb.physics.arguments import as_config
from otgb.physics.augmented import Augmented
from otgb.physics.base import PhysicsModel
from otgb.runs import Run

CONFIGS = Path(__file__).resolve().parents[2] / "configs"  # a clone's task configs (README installs from a clone)
BUILT_IN = {"Pendulum": "pendulum.yaml", "AdvectionDiffusion": "advdiff.yaml", "ReactionDiffusion": "reactdiff.yaml"}


class MissingEffect:
    """Find what a physics model lacks from its measurements.

    ``MissingEffect(physics, **settings)`` takes a :class:`~otgb.physics.PhysicsModel` built in Python (a pendulum,
    advection-diffusion or reaction-diffusion model, or one of them augmented), with the grey-box, critic and budget of
    the matching config in ``configs/``, and ``discover:`` settings as keywords
    (:class:`~otgb.discovery.settings.DiscoverySettings`: ``seed=1``, ``alpha=0.01``, ...). Any other physics:
    :meth:`from_config` with a config of your own.
    """

    def __init__(self, physics: PhysicsModel, **settings: Any) -> None:
        if not isinstance(physics, PhysicsModel):
            raise InputError(f"MissingEffect: physics={physics!r} is not an otgb.physics.PhysicsModel; expected one")
        self._files = [str(built_in_config(physics))]
        self._overrides = {"data.physics": as_config(physics)}  # rebuilt by the parser: its config, logs and checkpoints
        self._overrides |= {f"discover.{key}": value for key, value in checked_settings(settings).items()}

    @classmethod
    def from_config(cls, path: str | Path, overrides: Mapping[str, Any] | None = None) -> MissingEffect:
        """From a config file as ``otgb discover --config`` takes it, with ``overrides``: dotted keys as the command
        spells them and their values, e.g. ``{"data.simulation_budget": 8000, "discover.seed": 1}``."""
        if overrides is not None and not isinstance(overrides, Mapping):
            raise InputError(f"MissingEffect.from_config: overrides={overrides!r}; expected a mapping of dotted keys to values")
        finder = cls.__new__(cls)
        finder._files, finder._overrides = [str(Path(path).resolve())], dict(overrides or {})
        return finder

    def fit(self, measurements: Any, run_dir: str | Path | None = None) -> DiscoveryResult:
        """Discover what the physics lacks from ``measurements``: a file (``.csv``, ``.npz``, ``.pt``; each trajectory at
        its own times), a numpy array or torch tensor ``(N, T, *obs)`` on the model's time grid (NaN where a value was
        not measured), or a run of :func:`otgb.runs.load_run` (its measurements, and its loaded checkpoint as the
        grey-box). With ``run_dir``, the report's files, the grey-box's
        logs and checkpoints (``runs/<config stem>/version_N``) and the fit cache (``runs/<config stem>/fit_cache``:
        the same call resumes) go there; without, nothing is kept. Relative paths (the measurements' file, an override
        ending in ``_path``) are read from the working directory."""
        with working_folder(run_dir) as folder:
            measured, ckpt_path = measurements_in(measurements, folder)
            args = self._arguments(measured, ckpt_path)
            with inside(folder), naming_the_array(folder):  # the config's relative folders are the working folder's
                result = discover(build(args, {"prog": "otgb discover", "raise_input_errors": True}))
            if run_dir is not None:
                result.write(folder)
                return result
            return kept_in_memory(result, folder, measurements)

    def _arguments(self, measured: str, ckpt_path: str | None) -> list[str]:
        args = [arg for path in self._files for arg in ("--config", path)]
        args += ["--data.hidden_effect=[]", f"--data.measured_path={measured}"]
        args += [f"--{key}={as_argument(resolved(key, value))}" for key, value in self._overrides.items()]
        return args + ([f"--ckpt_path={ckpt_path}"] if ckpt_path else [])

    def __repr__(self) -> str:
        return f"MissingEffect.from_config({self._files[0]!r}, {self._overrides!r})"


def built_in_config(physics: PhysicsModel) -> Path:
    """The task config whose grey-box, critic and budget suit ``physics`` (an augmented model: its base's)."""
    base = physics.base if isinstance(physics, Augmented) else physics
    name = BUILT_IN.get(type(base).__name__)
    if name is None or not (CONFIGS / name).is_file():
        where = f"no built-in config for {type(base).__name__}" if name is None else f"{CONFIGS / name} is not there"
        raise InputError(
            f"MissingEffect({type(physics).__name__}(...)): {where}; give a config of your own: "
            "MissingEffect.from_config('my_model.yaml') (docs/own-physics.md)"
        )
    return CONFIGS / name


def checked_settings(settings: dict[str, Any]) -> dict[str, Any]:
    """``settings`` if each names a :class:`DiscoverySettings` parameter, else one line naming the closest."""
    known = list(inspect.signature(DiscoverySettings).parameters)
    for key in settings:
        if key not in known:
            close = closest(key, known)
            hint = f"; did you mean {', '.join(close)}?" if close else f"; expected one of {', '.join(known)}"
            raise InputError(f"MissingEffect: no discover setting {key!r}{hint}")
    return settings


def resolved(key: str, value: Any) -> Any:
    """A path an override gives (its key ends in ``_path``) made absolute, as the caller's working directory reads it:
    discovery runs in another folder."""
    if key.endswith("_path") and isinstance(value, (str, Path)):
        return str(Path(value).resolve())
    return value


def kept_in_memory(result: DiscoveryResult, folder: Path, measurements: Any) -> DiscoveryResult:
    """``result`` of a run whose working ``folder`` is removed: the report names no file in it (an array given is
    named as such, and no fit cache was kept) and a next round's file holds the array in its own order."""
    facts = {key: value for key, value in result.facts.items() if key != "fit_cache"}
    facts["description"] = facts["description"].replace(str(folder / "measured.npz"), ARRAY)
    if isinstance(measurements, (np.ndarray, torch.Tensor)):
        return replace(result, facts=facts, measured=torch.as_tensor(np.asarray(measurements)))
    return replace(result, facts=facts)


def as_argument(value: Any) -> str:
    """A value as the command line spells it: a string as it is, anything else as YAML on one line."""
    if isinstance(value, str):
        return value
    return yaml.safe_dump(value, default_flow_style=True, width=10**9).strip().removesuffix("\n...")


ARRAY = "the array given to MissingEffect.fit"


@contextmanager
def naming_the_array(folder: Path) -> Iterator[None]:
    """Within it, bad input that names the file an array was written to names the array instead."""
    try:
        yield
    except InputError as error:
        text = str(error)
        if str(folder / "measured.npz") not in text:
            raise
        raise InputError(text.replace(str(folder / "measured.npz"), ARRAY)) from None


@contextmanager
def inside(folder: Path) -> Iterator[None]:
    """Within it, ``folder`` is the working directory."""
    before = Path.cwd()
    os.chdir(folder)
    try:
        yield
    finally:
        os.chdir(before)


@contextmanager
def working_folder(run_dir: str | Path | None) -> Iterator[Path]:
    """``run_dir`` (made if missing), or a temporary folder removed afterwards."""
    if run_dir is not None:
        Path(run_dir).mkdir(parents=True, exist_ok=True)
        yield Path(run_dir).resolve()
        return
    with tempfile.TemporaryDirectory(prefix="otgb-discover-") as folder:
        yield Path(folder)


def measurements_in(measurements: Any, folder: Path) -> tuple[str, str | None]:
    """The file that ``data.measured_path`` reads for ``measurements``, and a grey-box checkpoint that comes with
    them (a loaded run's) or None. An array or tensor is written to ``folder/measured.npz``."""
    if isinstance(measurements, (str, Path)):
        return str(Path(measurements).resolve()), None
    if isinstance(measurements, Run):
        source, loaded = measurements.datamodule.source, getattr(measurements.model, "loaded_from", None)
        if isinstance(source, FileMeasurements):
            return str(Path(source.path).resolve()), loaded and str(Path(loaded).resolve())
        data = measurements.datamodule
        data.setup("fit")
        data.setup("test")
        measurements = torch.cat([data.measured, data.val_set["y"].flatten(0, 1), data.test_set["y"].flatten(0, 1)])
        return measurements_in(measurements, folder)[0], loaded and str(Path(loaded).resolve())
    if isinstance(measurements, (np.ndarray, torch.Tensor)):
        array = measurements.detach().cpu().numpy() if isinstance(measurements, torch.Tensor) else measurements
        path = folder / "measured.npz"
        np.savez(path, y=array)
        return str(path), None
    raise InputError(
        f"MissingEffect.fit: measurements of type {type(measurements).__name__}; expected a file path, a numpy array or "
        "torch tensor (N, T, *obs), or a run of otgb.runs.load_run"
    )
