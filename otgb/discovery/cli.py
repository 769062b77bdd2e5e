"""``otgb discover``: find where f_p and your measurements disagree, name the missing terms, add them, check.

    otgb discover --config my_model.yaml --data.measured_path measurements.npz [--ckpt_path grey-box.ckpt]

Time against precision: ``--data.simulation_budget`` (the grey-box's training: too small and
the report says it is undertrained), ``--discover.fit_steps`` and ``--discover.fit_batch`` (each
coefficient fit), ``--discover.n_permutations`` (the disagreement maps' p-values),
``--discover.families`` (fewer prior families, fewer fits), ``--ckpt_path`` (skip training).

It takes the options of ``otgb fit`` (the same config files work; with a config's hidden
effect and no file, the measurements are generated from that DGP, which the workflow does not
see, and the report adds pointwise errors against it), a ``discover:`` section
(:class:`otgb.discovery.settings.DiscoverySettings`) and ``--ckpt_path``, a grey-box trained on
the same measurements, to skip training. It writes ``report.md``, ``report.json``,
``figures/`` and ``augmented.yaml`` into the run directory (``runs/<config stem>/version_N``,
where the fit's logs and checkpoints also go) and prints that directory. Progress goes to stderr.
"""

from __future__ import annotations

import sys
from pathlib import Path

from otgb.discovery.pipeline import discover as run_discovery
from otgb.discovery.session import DescribedHelp, Stopped, build


def discover(args: list[str]) -> Path:
    """Run ``otgb discover`` with its command-line arguments: parse, discover, write the report into the run directory,
    then print the verdict and that directory on stdout. Returns the run directory."""
    parser = {"prog": "otgb discover", "description": _description(), "formatter_class": DescribedHelp}
    session = build(args, parser)
    try:
        result = run_discovery(session)
    except Stopped as stopped:
        print(stopped, file=sys.stderr)
        raise SystemExit(128 + stopped.signum) from None
    run_dir = result.write(session.log_dir)
    answer, *details = result.report["verdict_parts"]
    print(f"otgb discover: {answer}")
    for detail in details:
        print(f"  {detail}")
    print(f"otgb discover: report in {run_dir}")
    return run_dir


def _description() -> str:
    """What ``otgb discover`` does, an example, and which options trade time for precision (``--help``'s opening)."""
    opening, example, trade, _ = __doc__.split("\n\n", 3)
    return "\n\n".join([opening.replace("``", ""), example, trade.replace("``", "")])
