"""Test reports: ``metrics.json`` and a Markdown table per run, and tables across runs.

``metrics.json`` holds the run's facts and, for each source ("model", "fp" for f_p alone,
"reference"), every metric as ``{"mean": float, "std": float | null}``:

- ABS ERR / N-RMSE: mean and std over the test inputs (model, f_p); over the random
  splits for the Reference;
- MMD, MMD^2 at the median bandwidth, MMDAgg outputs: one value (std null) for model and
  f_p; mean and std over splits for the Reference (``mmdagg_reject`` there is the rejection
  rate over splits, which should be near alpha);
- C2ST: mean and std over the cross-validation folds (model, f_p); over splits (Reference).
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

SOURCES = {"model": "", "fp": "fp_", "reference": "ref_"}
HEADERS = {"model": "model", "fp": "f_p alone", "reference": "Reference"}
LABELS = {
    "abs_err": "ABS ERR",
    "nrmse": "N-RMSE",
    "mmd": "MMD (paper-code, 6 kernels)",
    "mmd2_median": "MMD^2_u (median bandwidth)",
    "mmdagg_reject": "MMDAgg rejects H0 (alpha 0.05)",
    "mmdagg_pvalue": "MMDAgg adjusted p-value",
    "mmdagg_mmd2": "MMDAgg MMD^2_u (selected bandwidth)",
    "c2st": "C2ST accuracy",
}


def split_sources(results: dict[str, float]) -> dict[str, dict[str, dict[str, float | None]]]:
    """Flat logged results (``fp_abs_err``, ``ref_c2st_std``, ...) -> {source: {metric: {mean, std}}}."""
    out: dict[str, dict[str, dict[str, float | None]]] = {source: {} for source in SOURCES}
    for source, prefix in SOURCES.items():
        for name in LABELS:
            key = prefix + name
            if key in results:
                std = results.get(f"{key}_std")
                out[source][name] = {"mean": float(results[key]), "std": None if std is None else float(std)}
    return out


def format_value(mean: float, std: float | None) -> str:
    if std is None or math.isnan(std):
        return f"{mean:.4g}"
    return f"{mean:.4g} ± {std:.2g}"


def markdown_table(by_source: dict[str, dict[str, dict[str, float | None]]]) -> str:
    names = [name for name in LABELS if any(name in by_source[s] for s in SOURCES)]
    lines = ["| metric | " + " | ".join(HEADERS[s] for s in SOURCES) + " |", "|---" * (len(SOURCES) + 1) + "|"]
    for name in names:
        cells = [format_value(**by_source[s][name]) if name in by_source[s] else "" for s in SOURCES]
        lines.append(f"| {LABELS[name]} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def write_report(run_dir: Path, run: dict[str, Any], results: dict[str, Any]) -> dict[str, Any]:
    """Write ``metrics.json`` and ``metrics.md`` into ``run_dir``; return the JSON content."""
    results = {k: float(v) for k, v in results.items()}
    by_source = split_sources(results)
    seconds = {source: results.get(f"{prefix}eval_seconds") for source, prefix in SOURCES.items()}
    content = {"run": run, **by_source, "seconds": seconds}
    run_dir.mkdir(parents=True, exist_ok=True)
    (run_dir / "metrics.json").write_text(json.dumps(content, indent=2) + "\n")
    header = (
        f"# Test metrics: {run.get('name')}\n\n"
        f"checkpoint `{run.get('ckpt_path')}` (step {run.get('global_step')}), {run.get('n_inputs')} test inputs x "
        f"{run.get('draws_per_input')} draws\n\n"
    )
    note = (
        "\nmean ± std: over test inputs (ABS ERR, N-RMSE) or C2ST folds for model and f_p; over "
        "random splits of two independent DGP draw sets for the Reference.\n"
    )
    (run_dir / "metrics.md").write_text(header + markdown_table(by_source) + note)
    return content
