"""The tutorials' pages done as written, at full size: their results and timings, and the tables the pages show.

    python scripts/walkthroughs.py run --page own-data          # docs/own-data.md's commands in bench/walkthroughs/
    python scripts/walkthroughs.py table --page own-data        # its results between the page's markers
    python scripts/walkthroughs.py run --page lab-data          # docs/lab-data.md: a lab's file, fitted and discovered

A page's files are its fenced blocks with a title (```python title="my_oscillator.py"), its commands
the lines of its ```bash blocks, run in order from a fresh folder as a shell would (``otgb`` is
``python -m otgb.cli``, ``/path/to/otgb`` this checkout, a glob such as ``best-step=*.ckpt``
expanded). ``run`` keeps each command's wall time and each ``otgb test`` report's ``metrics.md``
in ``results/walkthroughs/<page>/``; ``table`` writes what the page shows of them between its
markers (:func:`write_page`). The tests
(tests/test_docs.py) run the same commands at a seconds-long size with this module's helpers.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shlex
import shutil
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).parents[1]
RESULTS = ROOT / "results" / "walkthroughs"
END = "<!-- end results -->"
FIGURES = {"own-data": {"own-data-distributions.png": "runs/my_pendulum/version_0/figures/distributions_step*.png"}}


def files(text: str) -> dict[str, str]:
    """The titled code blocks of a page: file name -> content."""
    return {name: body + "\n" for name, body in re.findall(r'```\w+ title="([^"]+)"\n(.*?)\n```', text, re.S)}


def blocks(text: str, language: str) -> list[str]:
    return re.findall(rf"```{language}\n(.*?)\n```", text, re.S)


def commands(text: str) -> list[str]:
    return [line for block in blocks(text, "bash") for line in block.splitlines() if line.strip()]


def run(command: str, cwd: Path, extra: list[str] = (), env: dict[str, str] | None = None) -> subprocess.CompletedProcess:
    """One documented command line, as a shell would run it in ``cwd``; ``extra`` goes to every ``otgb`` command,
    ``env`` to its environment."""
    assert shlex.split(command)[0] in ("otgb", "python", "PYTHONPATH=."), command  # PYTHONPATH=.: the user's module
    program, *args = _words(command)
    args = [str(ROOT) + arg.removeprefix("/path/to/otgb") if arg.startswith("/path/to/otgb") else arg for arg in args]
    expanded = []
    for arg in args:  # the shell's glob, e.g. --ckpt_path runs/.../best-step=*.ckpt
        matches = sorted(cwd.glob(arg)) if "*" in arg else [arg]
        assert len(matches) == 1, f"{arg} matches {matches}"
        expanded.append(str(matches[0]))
    if program == "otgb":
        argv = [sys.executable, "-m", "otgb.cli", *expanded, *extra]
    else:
        assert program == "python", command
        argv = [sys.executable, *expanded]
    env = {**os.environ, **(env or {}), "PYTHONPATH": os.pathsep.join([str(ROOT), str(cwd)])}
    return subprocess.run(argv, cwd=cwd, env=env, capture_output=True, text=True)


def walk(page: str, folder: Path) -> None:
    """The page's files and commands in an empty ``folder``; timings and test reports into ``RESULTS / page``."""
    from otgb.runs import machine

    text = (ROOT / "docs" / f"{page}.md").read_text()
    shutil.rmtree(folder, ignore_errors=True)
    folder.mkdir(parents=True)
    for name, content in files(text).items():
        (folder / name).write_text(content)
    out = RESULTS / page
    shutil.rmtree(out, ignore_errors=True)
    out.mkdir(parents=True)
    timings = []
    for command in commands(text):
        started = time.time()
        done = run(command, folder, ["--trainer.enable_progress_bar=false"])
        if done.returncode != 0:
            raise SystemExit(f"walkthroughs: {command!r} failed (exit {done.returncode}):\n{done.stderr[-2000:]}")
        timings.append({"command": command, "wall_s": time.time() - started})
        kind = _words(command)[:2]
        if kind in (["otgb", "test"], ["otgb", "discover"]):
            name = "metrics.md" if kind[1] == "test" else "report.md"
            report = max(folder.glob(f"runs/*/version_*/{name}"), key=lambda p: p.stat().st_mtime)
            shutil.copy(report, out / f"{kind[1]}-{len(timings)}.md")
    for name, pattern in FIGURES.get(page, {}).items():  # the page's figure: the run's last of its kind
        shutil.copy(sorted(folder.glob(pattern))[-1], ROOT / "docs" / "figures" / name)
    (out / "timings.json").write_text(json.dumps({"commands": timings, "machine": machine()}, indent=1))
    print(f"walkthroughs: {page} done; results in {out}")


def sections(page: str) -> dict[str, str]:
    """What the page shows from its run: per ``otgb test`` (``test-N``, N its command's place) the report's summary
    sentence, metric table and legend; per ``otgb discover`` (``discover-N``) its report's verdict, named terms and
    gap table; and the commands' wall times (``timings``)."""
    out = RESULTS / page
    shown = {}
    for report in out.glob("test-*.md"):
        paragraphs = report.read_text().split("\n\n")
        at = next(i for i, p in enumerate(paragraphs) if p.startswith("| metric |"))
        shown[report.stem] = "\n\n".join(p for p in paragraphs[at - 1 : at + 2] if not p.startswith("checkpoint "))
    for report in out.glob("discover-*.md"):
        summary = report.read_text().split("## Where f_p", 1)[0].split("\n", 1)[1].strip()
        shown[report.stem] = re.sub(r"^## (.+)$", r"**\1**", summary, flags=re.M)  # the page's headings stay its own
    timing = json.loads((out / "timings.json").read_text())
    walls = "; ".join(f"`{_short(t['command'])}` {_duration(t['wall_s'])}" for t in timing["commands"])
    shown["timings"] = f"Wall times of the commands above, in order ({timing['machine']}): {walls}."
    return shown


def write_page(page: str) -> None:
    """Each section between the page's markers ``<!-- results: scripts/walkthroughs.py <name> -->`` and ``END``."""
    from otgb.reports import write_between

    doc = ROOT / "docs" / f"{page}.md"
    for name, text in sections(page).items():
        start = f"<!-- results: scripts/walkthroughs.py {name} -->"
        if start in doc.read_text():
            write_between(doc, start, END, text)


def _words(command: str) -> list[str]:
    """The command's words without a leading ``PYTHONPATH=.``."""
    words = shlex.split(command, comments=True)  # a documented command may end with a comment
    return words[1:] if "=" in words[0] else words


def _short(command: str) -> str:
    words = _words(command)
    return " ".join(words[:2]) if words[0] == "otgb" else f"python {Path(words[1]).name}"


def _duration(seconds: float) -> str:
    return f"{seconds:.0f} s" if seconds < 120 else f"{seconds / 60:.1f} min"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("step", choices=["run", "table"])
    parser.add_argument("--page", required=True, choices=["own-data", "own-physics", "lab-data"])
    parser.add_argument("--folder", type=Path, default=ROOT / "bench" / "walkthroughs", help="run: where the page runs")
    args = parser.parse_args()
    if args.step == "run":
        walk(args.page, args.folder / args.page)
    else:
        write_page(args.page)
        print(f"walkthroughs: rewrote the results of docs/{args.page}.md")


if __name__ == "__main__":
    main()
