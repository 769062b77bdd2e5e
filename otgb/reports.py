"""Test reports: ``metrics.json`` and a Markdown table per run, and tables across runs.

``metrics.json`` holds the run's facts (``run``, including the evaluation ``mode``: "joint"
against a known DGP, or "marginal" against held-out measurements) and, for each source
("model", "fp" for f_p alone, "reference"), every metric as ``{"mean": float, "std": float | null}``
(``joint_<name>``: the metrics on rows (recorded inputs, y) of a measured file that recorded
the inputs):

- ABS ERR / N-RMSE: mean and std over the test inputs (model, f_p); over the random
  splits for the Reference;
- MMD, MMD^2 at the median bandwidth, MMDAgg outputs: one value (std null) for model and
  f_p; mean and std over splits for the Reference (``mmdagg_reject`` there is the rejection
  rate over splits, which should be near alpha);
- C2ST: mean and std over the cross-validation folds (model, f_p); over splits (Reference).

Where the draws were made on the test measurements' own recorded inputs (``run.across_halves``),
the metrics without ``joint_`` score model and f_p over the Reference's splits too: mean and std
over them, ``mmdagg_reject`` a rate.

``per_time`` holds the energy distance per time step and observed component for each source,
(T, C) lists, with the ``times`` and ``components`` they belong to.
"""

from __future__ import annotations

import json
import math
import statistics
from pathlib import Path
from typing import Any

SOURCES = {"model": "", "fp": "fp_", "reference": "ref_"}
HEADERS = {"model": "model", "fp": "f_p alone", "reference": "Reference"}
UNTRAINED = "no checkpoint was given, so the model is the map as initialised, not a trained one"
GROUPS = {"": "", "joint_": "joint with recorded inputs: "}  # metric-name prefix -> row label prefix
LABELS = {
    "abs_err": "ABS ERR",
    "nrmse": "N-RMSE",
    "mmd": "MMD (paper-code, 6 kernels)",
    "mmd2_median": "MMD^2_u (median bandwidth)",
    "energy": "Energy distance (standardised rows)",
    "mmdagg_reject": "MMDAgg rejects H0 (alpha 0.05)",
    "mmdagg_pvalue": "MMDAgg adjusted p-value",
    "mmdagg_mmd2": "MMDAgg MMD^2_u (selected bandwidth)",
    "c2st": "C2ST accuracy",
}

BETTER = {
    "abs_err": "lower",
    "nrmse": "lower",
    "mmd": "lower, to the Reference",
    "mmd2_median": "lower, to the Reference (unbiased: below 0 is noise)",
    "energy": "lower, to the Reference (unbiased: below 0 is noise)",
    "mmdagg_reject": "no (yes: the samples differ)",
    "mmdagg_pvalue": "higher (below 0.05: they differ)",
    "mmdagg_mmd2": "lower, to the Reference (unbiased: below 0 is noise)",
    "c2st": "0.5: cannot be told apart; 1: always can",
}
HEADLINE = ("c2st", "energy", "abs_err")  # the summary sentence's metric: the first one present


def split_sources(results: dict[str, float]) -> dict[str, dict[str, dict[str, float | None]]]:
    """Flat logged results (``fp_abs_err``, ``ref_c2st_std``, ``joint_mmd``, ...) -> {source: {metric: {mean, std}}}."""
    out: dict[str, dict[str, dict[str, float | None]]] = {source: {} for source in SOURCES}
    for source, prefix in SOURCES.items():
        for name in metric_names():
            key = prefix + name
            if key in results:
                std = results.get(f"{key}_std")
                out[source][name] = {"mean": float(results[key]), "std": None if std is None else float(std)}
    return out


def metric_names() -> list[str]:
    return [group + name for group in GROUPS for name in LABELS]


def label(name: str) -> str:
    group = next(g for g in sorted(GROUPS, key=len, reverse=True) if name.startswith(g))
    return GROUPS[group] + LABELS[name.removeprefix(group)]


def write_between(doc: Path, start: str, end: str, text: str) -> None:
    """Replace what lies between the marker lines ``start`` and ``end`` of the page ``doc`` by ``text``."""
    head, _, rest = doc.read_text().partition(start)
    _, _, tail = rest.partition(end)
    doc.write_text(f"{head}{start}\n{text.rstrip()}\n{end}{tail}")


def mean_spread(values: list[float], plus: str = "±", empty: str = "") -> str:
    """One value as it is; several as mean ± standard deviation (over seeds or runs)."""
    if not values:
        return empty
    if len(values) == 1:
        return f"{values[0]:.4g}"
    return f"{statistics.mean(values):.4g} {plus} {statistics.stdev(values):.2g}"


def format_value(mean: float, std: float | None, name: str = "", source: str = "model") -> str:
    if name.endswith("mmdagg_reject"):  # a test's decision: yes / no; over splits (a spread given), a rate
        return f"rejects in {mean:.0%} of splits" if std is not None else ("yes" if mean >= 0.5 else "no")
    if std is None or math.isnan(std):
        return f"{mean:.4g}"
    return f"{mean:.4g} ± {std:.2g}"


def markdown_table(by_source: dict[str, dict[str, dict[str, float | None]]]) -> str:
    names = [name for name in metric_names() if any(name in by_source[s] for s in SOURCES)]
    lines = ["| metric | better | " + " | ".join(HEADERS[s] for s in SOURCES) + " |", "|---" * (len(SOURCES) + 2) + "|"]
    for name in names:
        cells = [format_value(**by_source[s][name], name=name, source=s) if name in by_source[s] else "" for s in SOURCES]
        better = BETTER[name.removeprefix("joint_")]
        lines.append(f"| {label(name)} | {better} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def summary(by_source: dict[str, dict[str, dict[str, float | None]]]) -> str:
    """One sentence: the headline metric for the model, f_p alone and the Reference, and the share of f_p's distance
    to the Reference that the model closes. Where the model is no closer than f_p by the first headline metric (a
    C2ST at 1 for both, say), the next one present says how far each is."""
    names = [n for n in HEADLINE if all(n in by_source[s] for s in SOURCES)]
    if not names:
        return ""
    sentence, state = _summary_clause(names[0], by_source)
    if state == "no closer" and len(names) > 1:
        sentence += "; " + _summary_clause(names[1], by_source)[0]
    if state == "f_p at the floor" and by_source["fp"].get("mmdagg_reject", {}).get("mean", 0.0) >= 0.5:
        p_value = by_source["fp"].get("mmdagg_pvalue", {}).get("mean", math.nan)
        sentence += f"; yet the MMDAgg test tells f_p alone from the held-out data (adjusted p-value {p_value:.2g})"
    return sentence + ".\n\n"


def _summary_clause(name: str, by_source: dict[str, dict[str, dict[str, float | None]]]) -> tuple[str, str]:
    """The clause of ``name`` and where it puts the model: ``f_p at the floor``, ``at the floor``, ``no closer`` (than
    f_p) or ``closer``."""
    model, fp, ref = (by_source[s][name]["mean"] for s in SOURCES)
    spread = by_source["reference"][name].get("std")  # how much the floor itself varies at this sample size
    noise = f" ± {spread:.2g}" if spread is not None and math.isfinite(spread) and spread > 0 else ""
    values = f"{LABELS[name]}: model {model:.3g}, f_p alone {fp:.3g}, Reference (noise floor) {ref:.3g}{noise}"
    if not math.isfinite(fp - ref) or fp <= ref:
        return f"{values}: by this metric f_p alone is already at the noise floor", "f_p at the floor"
    if model <= ref:  # below the floor: the sampling noise of small held-out sets, not a model better than the data
        text = f"{values}: the model is at the noise floor (no further from the held-out data than the Reference)"
        return text, "at the floor"
    if model >= fp:
        return f"{values}: the model is no closer to the noise floor than f_p alone", "no closer"
    return f"{values}: the model closes {(fp - model) / (fp - ref):.0%} of f_p's distance to the noise floor", "closer"


def summary_of(run_dir: Path) -> str:
    """The summary sentence of the report in ``run_dir`` (:func:`summary`); empty where there is none."""
    path = run_dir / "metrics.json"
    if not path.is_file():
        return ""
    content = json.loads(path.read_text())
    sentence = summary({source: content.get(source, {}) for source in SOURCES}).strip()
    run = content.get("run", {})
    caveats = [UNTRAINED] if run.get("untrained") else []
    caveats += [elsewhere(run["trained_on"])] if run.get("trained_on") else []
    return f"{sentence[:-1]} ({'; '.join(caveats)})." if sentence and caveats else sentence


def checkpoint_text(run: dict[str, Any]) -> str:
    """The checkpoint a report scored, or that there was none."""
    return f"checkpoint `{run['ckpt_path']}`" if run.get("ckpt_path") else "no checkpoint"


def elsewhere(trained_on: str) -> str:
    """The caveat of a report on a checkpoint that was trained on other measurements than those it was scored on."""
    return f"the checkpoint was trained on {trained_on}, not on these measurements"


def per_time_section(per_time: dict[str, Any], times: list[float], components: list[str]) -> str:
    """Where in time each source differs most from the measured data (energy distance per step)."""
    lines = ["| component | " + " | ".join(f"{HEADERS[s]}: max at t (value)" for s in SOURCES if s in per_time) + " |"]
    lines.append("|---" * (1 + sum(s in per_time for s in SOURCES)) + "|")
    for c, component in enumerate(components):
        cells = []
        for source in (s for s in SOURCES if s in per_time):
            column = [row[c] for row in per_time[source]]
            step = max(range(len(column)), key=column.__getitem__)
            cells.append(f"t = {times[step]:.3g} ({column[step]:.3g})")
        lines.append(f"| {component} | " + " | ".join(cells) + " |")
    return "\nEnergy distance per time step (in the observation's units; all steps in metrics.json `per_time`):\n\n" + (
        "\n".join(lines) + "\n"
    )


def write_report(
    run_dir: Path,
    run: dict[str, Any],
    results: dict[str, Any],
    per_time: dict[str, Any] | None = None,
    labels: dict[str, list] | None = None,
) -> dict[str, Any]:
    """Write ``metrics.json`` and ``metrics.md`` into ``run_dir``; return the JSON content.

    ``per_time``: vector results such as ``energy_per_time`` / ``fp_energy_per_time`` (T, C);
    ``labels``: their ``times`` and ``components``.
    """
    results = {k: float(v) for k, v in results.items()}
    by_source = split_sources(results)
    seconds = {source: results.get(f"{prefix}eval_seconds") for source, prefix in SOURCES.items()}
    content: dict[str, Any] = {"run": run, **by_source, "seconds": seconds}
    vectors = {
        s: per_time[f"{p}energy_per_time"].tolist() for s, p in SOURCES.items() if f"{p}energy_per_time" in (per_time or {})
    }
    if vectors:
        content["per_time"] = {"statistic": "energy distance", **(labels or {}), **vectors}
    run_dir.mkdir(parents=True, exist_ok=True)
    (run_dir / "metrics.json").write_text(json.dumps(content, indent=2) + "\n")
    header = (
        f"# Test metrics: {run.get('name')}\n\n"
        f"Evaluation mode **{run.get('mode')}**: {run.get('description', '')}\n\n"
        f"{checkpoint_text(run)} (step {run.get('global_step')}), {run.get('sample_sizes')}\n\n"
    )
    if run.get("untrained"):
        header += f"**Note: {UNTRAINED}: give `--ckpt_path` a checkpoint of a fit to test it.**\n\n"
    if run.get("trained_on"):
        header += f"**Note: {elsewhere(run['trained_on'])}.**\n\n"
    over = ("test inputs (ABS ERR, N-RMSE) or " if "abs_err" in by_source["model"] else "") + "C2ST folds"
    note = f"\nmean ± std: over {over} for model and f_p; over {run.get('reference_note')} for the Reference.\n"
    if run.get("across_halves"):
        note += (
            "The rows without recorded inputs score the model and f_p across the Reference's splits: the draws on one "
            "half's recorded inputs against the other half's measurements (mean ± std over the splits), since a draw "
            "made on a measurement's own inputs sits next to it and whole-sample statistics would read that as alike.\n"
        )
    section = per_time_section(vectors, labels["times"], labels["components"]) if vectors and labels else ""
    (run_dir / "metrics.md").write_text(header + summary(by_source) + markdown_table(by_source) + note + section)
    return content
