"""The discovery's files: ``report.json``, ``report.md`` with its figures, ``augmented.yaml``."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import yaml

from otgb.analysis.components import to_json
from otgb.analysis.figures import close, components_figure, disagreement_figure, distribution_figure, save
from otgb.discovery.families import centre
from otgb.discovery.forms import parameter_records
from otgb.discovery.library import implausible, term_name
from otgb.discovery.locate import DisagreementMap
from otgb.discovery.markdown import markdown
from otgb.discovery.prior_text import distribution, prior_dict
from otgb.discovery.record import Discovery
from otgb.discovery.stages import markdown_rows
from otgb.discovery.verdict import confirmed, kept_terms, named_divergences, outcome, verdict
from otgb.physics.augmented import Augmented
from otgb.physics.base import PhysicsModel


def report_dict(result: Discovery, physics: PhysicsModel, facts: dict[str, Any]) -> dict[str, Any]:
    """``report.json``: found, verdict, terms, ambiguous, explained_r2, gap, and the details."""
    parts = verdict(result, physics)
    return {
        "outcome": outcome(result),
        "found": result.found,
        "confirmed": confirmed(result),
        "verdict": "; ".join(parts),
        "verdict_parts": parts,
        "terms": _term_dicts(result, physics),
        "recalibrated": _recalibrated_dicts(result) if result.recalibrated else [],
        "recalibration": _recalibration_evidence(result),
        "forms": _forms_dict(result),
        "ambiguous": _ambiguous(result, physics),
        "evidence": [_comparison_dict(c, physics) for c in result.evidence],
        "added_by_evidence": result.added,
        "explained_r2": {s.component: s.explained_r2 for s in result.selections},
        "gap": result.gap,
        "closer": result.closer.to_dict() if result.closer else None,
        "locate": {
            "before": result.before.to_dict(),
            "sentence_before": result.sentence_before,
            "after": result.after.to_dict() if result.after else None,
            "sentence_after": result.sentence_after,
            "paired_after": result.paired_after.to_dict() if result.paired_after else None,
        },  # fmt: skip
        "regression": [_selection_dict(s) for s in result.selections],
        "cross_check": result.cross_check,
        "route": result.route if result.found else None,
        "search_reason": result.search_reason,
        "search": [_search_step_dict(step) for step in result.search],
        "theta_search": _theta_search_dict(result.theta_search),
        "evidence_on": result.evidence_on,
        "search_unsupported": _unsupported_dicts(result.unsupported),
        **_family_dict(result),
        "dropped_by_heldout_check": result.dropped,
        "interval_method": result.intervals.method if result.intervals else None,
        "diverged": [d | {"named": d in named_divergences(result)} for d in result.diverged],
        "undertrained": result.undertrained,
        "correction_share": result.correction_share,
        "pointwise": result.pointwise,
        "run": facts,
    }


def _term_dicts(result: Discovery, physics: PhysicsModel) -> list[dict[str, Any]]:
    """Each named term: its physical name, coefficient with interval, distribution, and f_phi's regression figures."""
    regression = {(t.candidate.feature, t.candidate.component): t for t in result.final_terms}
    intervals = result.intervals
    excluded = result.family.excluded_spread if result.family else None
    adopted = result.forms.adopted if result.forms else None
    terms = []
    for i, (candidate, prior) in enumerate(kept_terms(result)):
        middle = centre(prior)
        found = regression.get((candidate.feature, candidate.component))
        form = adopted if adopted is not None and adopted.candidate == candidate else None
        terms.append(
            {
                "name": term_name(candidate, middle, physics),
                "feature": candidate.feature,
                "component": candidate.component,
                "coefficient": middle,
                "interval": list(intervals.centre[i]) if intervals else None,
                "interval_missing": None if intervals else NO_INTERVAL,
                "spread_interval": list(intervals.width[i]) if intervals and intervals.width else None,
                "inclusion_probability": found.inclusion_probability if found else None,
                "r2_share": found.r2_share if found else None,
                "regression_coefficient": found.coefficient if found else None,
                "regression_interval": list(found.interval) if found else None,
                "per_trajectory": found.per_trajectory if found else None,
                "distribution": distribution(prior),
                "excluded_spread": excluded[i] if excluded else None,
                "flag": implausible(candidate.feature, candidate.component, middle, physics),
                "parameters": parameter_records(form) if form else [],
            }
        )
    return terms


NO_INTERVAL = (
    "the sandwich could not be computed: the fit's discrepancy is not at a minimum there (its Hessian is not positive "
    "definite), or a model perturbed around the fit diverged (report.json's diverged lists it)"
)


def _search_step_dict(step: Any) -> dict[str, Any]:
    """One size of the library search: its terms, how well they fit g, its held-out score against f_p alone."""
    return {
        "terms": [{"feature": c.feature, "component": c.component} for c in step.candidates],
        "g_residual": step.g_residual,
        "heldout_energy": step.fitted.heldout_energy,
        "below_f_p": step.versus_f_p[0],
        "standard_error": step.versus_f_p[1],
        "validation_trajectories": len(step.fitted.heldout.rows),
        "alternatives": [[{"feature": c.feature, "component": c.component} for c in a] for a in step.alternatives],
    }


def _theta_search_dict(theta: Any) -> dict[str, Any] | None:
    """The search on theta-dependent terms, where it ran: why, its path, what it kept (None: the answer stayed) and by
    how much that fits the validation part better than the answer."""
    if theta is None:
        return None
    kept = None if theta.kept is None else [{"feature": c.feature, "component": c.component} for c in theta.kept.candidates]
    better, error = theta.versus_answer
    return {
        "reason": theta.reason,
        "path": [_search_step_dict(step) for step in theta.steps],
        "unsupported": _unsupported_dicts(theta.unsupported),
        "kept": kept,
        "below_answer": better if kept else None,
        "standard_error": error if kept else None,
    }


def _unsupported_dicts(unsupported: list) -> list[dict[str, Any]]:
    """The terms a library search dropped because their coefficients' 95 % intervals hold zero."""
    return [
        {"feature": u.candidate.feature, "component": u.candidate.component, "coefficient": u.coefficient,
         "interval": list(u.interval)}
        for u in unsupported
    ]  # fmt: skip


def _recalibrated_dicts(result: Discovery) -> list[dict[str, Any]]:
    """Each refitted prior of f_p: the parameter, the fitted prior (its kind and parameters) and the config's, and
    the 95 % intervals of its centre, of its width (where it varies) and of a uniform prior's bounds."""
    records = []
    for r in result.recalibration.parameters:
        bounds = r.bounds_intervals
        records.append({
            "parameter": r.parameter,
            "prior": {"kind": r.prior.kind.lower(), **r.prior.init_args},
            "config_prior": {"kind": r.before.kind.lower(), **dict(r.before.init_args)},
            "interval": list(r.centre_interval) if r.centre_interval else None,
            "width_interval": list(r.width_interval) if r.width_interval else None,
            "bounds_intervals": [list(b) for b in bounds] if bounds else None,
        })  # fmt: skip
    return records


def _forms_dict(result: Discovery) -> dict[str, Any] | None:
    """Why the parametric forms were weighed, each one's fit against the linear terms, and the one adopted."""
    if result.forms is None or result.forms.reason is None:
        return None
    adopted = result.forms.adopted
    return {"reason": result.forms.reason, "tried": [fit.to_dict() for fit in result.forms.tried],
            "adopted": adopted.candidate.feature if adopted else None,
            "alike": [fit.to_dict()["feature"] for fit in result.forms.alike_fits]}  # fmt: skip


def _recalibration_evidence(result: Discovery) -> dict[str, Any] | None:
    """How far below f_p alone's the recalibrated f_p's validation score lies, and whether it is the answer."""
    if result.recalibration is None:
        return None
    below, error = result.recalibration.below_f_p
    return {"below_f_p": below, "standard_error": error, "adopted": result.recalibrated,
            "kept_as_given": result.recalibration.kept_as_given}  # fmt: skip


def _family_dict(result: Discovery) -> dict[str, Any]:
    """The prior family chosen, each family's training discrepancy and difference to it, and those stopped short."""
    family = result.family
    return {
        "family": result.fitted.family if result.fitted else None,
        "family_training_discrepancy": family.scores if family else {},
        "family_difference": {f: {"difference": d, "standard_error": e} for f, (d, e) in family.differences.items()}
        if family
        else {},
        "family_stopped_short": family.stopped_short if family else [],
        "family_rejected": family.rejected if family else {},
    }


def _comparison_dict(comparison: Any, physics: PhysicsModel) -> dict[str, Any]:
    return {
        "feature": comparison.replaced.feature,
        "component": comparison.replaced.component,
        "alternative": comparison.by.feature,
        "alternative_name": term_name(comparison.by, comparison.coefficient, physics),
        "alternative_coefficient": comparison.coefficient,
        "difference": comparison.difference,
        "standard_error": comparison.standard_error,
        "standard_errors": comparison.standard_errors,
        "ambiguous": comparison.ambiguous,
    }


def _ambiguous(result: Discovery, physics: PhysicsModel) -> list[dict[str, Any]]:
    """Per kept term, the alternatives that the validation measurements cannot tell from it, with their numbers."""
    entries = []
    for candidate in result.fitted.candidates if result.found else []:
        mine = sorted((c for c in result.evidence if c.replaced == candidate and c.ambiguous), key=lambda c: c.standard_errors)
        close = [_comparison_dict(c, physics) for c in mine]
        if close:
            entries.append({"feature": candidate.feature, "component": candidate.component, "alternatives": close})
    return entries


def _selection_dict(selection: Any) -> dict[str, Any]:
    return {
        "component": selection.component,
        "selected": [t.candidate.feature for t in selection.terms],
        "explained_r2": selection.explained_r2,
        "condition_number": selection.condition_number,
        "confusable_pairs": [{"a": a, "b": b, "correlation": c} for a, b, c in selection.confusable_pairs],
        "inclusion_probability": selection.inclusion,
        "target_rms": selection.target_rms,
    }


def draw_locate(result: Discovery, path: Path, time_label: str) -> None:
    figure = disagreement_figure(disagreement_panels(result), time_label)
    save(figure, path)
    close(figure)


def disagreement_panels(result: Discovery) -> list[tuple[DisagreementMap, str]]:
    """The disagreement maps and their titles: f_p on the training part (where discovery looked) and, once terms
    are named, f_p (before) and the augmented physics (after) on the test part, which no fit saw: the same
    trajectories, so the last two panels compare like with like."""
    maps = [(result.before, f"f_p vs measured: the training part, {result.before.measured_trajectories}")]
    if result.before_on_test:
        test = f"the test part, {result.before_on_test.measured_trajectories}"
        maps.append((result.before_on_test, f"before: f_p vs measured, {test}"))
    if result.after:
        maps.append((result.after, f"after: augmented vs measured, the test part, {result.after.measured_trajectories}"))
    return maps


def write_report(
    run_dir: Path, result: Discovery, physics: PhysicsModel, facts: dict[str, Any], samples: dict, components: dict | None = None,
    stages: dict | None = None,
) -> dict:  # fmt: skip
    """Write report.json, report.md and the figures into ``run_dir``; returns the report dict.

    ``components``: the grey-box's component analysis (:func:`otgb.analysis.components.component_analysis`),
    written as ``components.json`` and ``figures/components.png`` and summarised in the report. ``stages``: where the
    run's time went (:mod:`otgb.discovery.stages`), written as ``stages.json`` and report.md's last section; not in
    report.json, whose numbers a seed fixes.
    """
    figures = run_dir / "figures"
    figures.mkdir(parents=True, exist_ok=True)
    report = report_dict(result, physics, facts)
    report["components"] = None if components is None else to_json(components)["summary"]
    if components is not None:
        (run_dir / "components.json").write_text(json.dumps(to_json(components), indent=2))
        figure = components_figure(components)
        save(figure, figures / "components.png")
        close(figure)
    (run_dir / "report.json").write_text(json.dumps(report, indent=2))
    draw_locate(result, figures / "disagreement.png", physics.axis_label("t"))
    names = [physics.axis_label(name) for name in physics.observed]
    figure = distribution_figure(samples, physics.observation_times(), names, time_label=physics.axis_label("t"))
    save(figure, figures / "distributions.png")
    close(figure)
    (run_dir / "report.md").write_text(markdown(report, facts) + "\n".join(markdown_rows(stages)) + "\n" * bool(stages))
    if stages is not None:
        (run_dir / "stages.json").write_text(json.dumps(stages, indent=2) + "\n")
    return report


def augmented_config(config: dict[str, Any], physics: PhysicsModel, result: Discovery) -> dict[str, Any]:
    """The run's config with ``data.physics`` replaced by f_p plus the named terms (earlier rounds' kept)."""
    config = {k: v for k, v in config.items() if k not in ("discover", "ckpt_path", "config")}
    physics_entry = config["data"]["physics"]
    earlier = []
    if isinstance(physics, Augmented):
        physics_entry, earlier = physics_entry["init_args"]["base"], physics_entry["init_args"]["terms"]
    if result.recalibrated:  # f_p's refitted priors replace the config's
        physics_entry = {**physics_entry, "init_args": dict(physics_entry.get("init_args") or {})}
        physics_entry["init_args"].update({r.parameter: prior_dict(r.prior) for r in result.recalibration.parameters})
    new = [
        {"class_path": "otgb.physics.LibraryTerm",
         "init_args": {"feature": c.feature, "component": c.component, "coefficient": prior_dict(p)}}
        for c, p in kept_terms(result)
    ]  # fmt: skip
    config["data"]["physics"] = {
        "class_path": "otgb.physics.Augmented",
        "init_args": {"base": physics_entry, "terms": earlier + new},
    }
    for logger in config["trainer"].get("logger") or []:  # the next round's logs: runs/augmented/<a new version_N>
        if isinstance(logger, dict) and "name" in logger.get("init_args", {}):
            logger["init_args"].update(name="auto", version=None)
    return config


def write_augmented(path: Path, config: dict[str, Any]) -> None:
    header = "# Written by otgb discover: the run's config with f_p augmented by the named terms.\n"
    path.write_text(header + yaml.safe_dump(config, sort_keys=False))
