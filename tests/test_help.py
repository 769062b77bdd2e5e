"""`otgb fit --help` documents every option of the model, the data, the evaluation, checkpointing and the component analysis;
`otgb discover --help` those of the discovery too.

jsonargparse takes each option's help from the constructor's Google-style ``Args:`` entry of
that parameter: an entry that packs several names on one line ("n_val, n_test: ...") leaves
them without help, and a second "name: ..." on the same line ends up in the first one's help.
"""

import os
import re
import subprocess
import sys
from collections import defaultdict
from pathlib import Path

import pytest

ROOT = Path(__file__).parents[1]
GROUPS = ("model", "data", "evaluation", "checkpoint", "components", "discover")
OPTION = re.compile(rf"--(?:{'|'.join(GROUPS)})\.[\w.]+")
TYPE_NOTE = re.compile(r"\((?:required, )?type: ")  # what jsonargparse appends: "(type: int, default: 0)"

SAMPLE = """\
Learns T_phi(x; theta, z) by kernel weak OT against a critic f_psi:
  --model CONFIG        Path to a configuration file.
  --model.transport_map.help [CLASS_PATH_OR_NAME]
                        Show the help for the given subclass of Module and exit.
  --model.transport_map TRANSPORT_MAP
                        builds the map from (physics, z_dim). (required, type: Callable[[PhysicsModel, int], Module], known
                        subclasses: torch.nn.Module, otgb.physics.Pendulum)
  --model.z_dim Z_DIM   size of the latent z; 0 for a deterministic map. (type: int, default: 0)
  --model.latent LATENT
                        distribution eta of z: "normal" (N(0, I)) or "uniform"
                        (U(-1, 1)). (type: str, default: normal)
  --data.hidden_effect [ITEM,...], --data.hidden_effect+ [ITEM,...]
                        the terms the DGP adds to f_p. (type: Sequence[Term], default: ())
  --data.n_val N_VAL    (type: int, default: 200)
  --data.stream_seed STREAM_SEED
                        (type: int | null, default: null)

Linked arguments:
  model.t_max --> data.batches_per_step [applied on parse]
                        map updates per critic update. (type: int)
"""


def option_help(text: str) -> dict[str, str]:
    """{option: its help without the type note} for every ``--<group>.<name>`` option of an argparse help.

    An entry starts at a line "  --option ..." and goes on over the lines indented deeper. Its
    help follows the invocation after a run of spaces, on the first line (short invocations) or
    the next ones. The ``.help`` entries (jsonargparse's subclass help printers) are left out.
    """
    entries: dict[str, list[str]] = {}
    current: list[str] | None = None
    for line in text.splitlines():
        if line.startswith("  -"):
            invocation, *rest = re.split(r"\s{2,}", line.strip(), maxsplit=1)
            name = invocation.split()[0].rstrip(",")
            current = None
            if OPTION.fullmatch(name) and not name.endswith(".help"):
                current = entries.setdefault(name, [])
                current.extend(rest)
        elif current is not None and line.startswith("   "):
            current.append(line.strip())
        else:
            current = None
    return {name: TYPE_NOTE.split(" ".join(parts), maxsplit=1)[0].strip() for name, parts in entries.items()}


def help_text(*subcommand: str) -> str:
    """The real command's help, on a wide terminal so that lines do not wrap, for this checkout's code."""
    env = {**os.environ, "COLUMNS": "200", "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
    command = [sys.executable, "-m", "otgb.cli", *subcommand, "--help"]
    return subprocess.run(command, capture_output=True, text=True, check=True, env=env, cwd=ROOT).stdout


def command_help(subcommand: str) -> dict[str, str]:
    """A subcommand's options with their help."""
    return option_help(help_text(subcommand))


@pytest.fixture(scope="module")
def fit_help() -> dict[str, str]:
    return command_help("fit")


def test_discover_help_documents_its_own_section():
    """`otgb discover --help`: the fit options plus the discover section, each with help of its own."""
    options = command_help("discover")
    discover = {name: text for name, text in options.items() if name.startswith("--discover.")}
    assert {"--discover.alpha", "--discover.n_permutations", "--discover.families"} <= set(discover)
    assert all(discover.values()), [name for name, text in discover.items() if not text]
    assert len(set(discover.values())) == len(discover), "two discover options share their help"
    assert "--data.measured_path" in options


def test_option_help_reads_jsonargparse_entries():
    assert option_help(SAMPLE) == {
        "--model.transport_map": "builds the map from (physics, z_dim).",
        "--model.z_dim": "size of the latent z; 0 for a deterministic map.",
        "--model.latent": 'distribution eta of z: "normal" (N(0, I)) or "uniform" (U(-1, 1)).',
        "--data.hidden_effect": "the terms the DGP adds to f_p.",
        "--data.n_val": "",
        "--data.stream_seed": "",
    }


def test_help_lists_the_options_of_each_group(fit_help):
    """Guards the parser: the options must be found at all, class-typed ones included."""
    expected = ("--model.transport_map", "--model.critic", "--model.objective", "--data.physics", "--data.seed")
    expected += ("--evaluation.seed",)
    for name in expected:
        assert name in fit_help, f"{name} not found in `otgb fit --help`: has jsonargparse's format changed?"


def test_every_option_has_help_of_its_own(fit_help):
    missing = sorted(name for name, text in fit_help.items() if not text)
    assert not missing, f"options without help text (give each parameter its own `Args:` line): {missing}"


def test_no_help_holds_another_parameters_entry(fit_help):
    """E.g. "seed: seed of the sets. stream_seed: seed of the stream" on one line: all of it is --data.seed's help."""
    swallowed = {}
    for name, text in fit_help.items():
        group = name.split(".")[0]
        others = [o.split(".", 1)[1] for o in fit_help if o.startswith(group + ".") and o != name]
        hits = [o for o in others if re.search(rf"(?<![\w.]){re.escape(o)}:", text)]
        if hits:
            swallowed[name] = hits
    assert not swallowed, f"help texts that hold other parameters' `Args:` entries: {swallowed}"


def test_no_two_options_of_a_group_share_their_help(fit_help):
    by_text: dict[tuple[str, str], list[str]] = defaultdict(list)
    for name, text in fit_help.items():
        if text:
            by_text[name.split(".")[0], text].append(name)
    shared = [names for names in by_text.values() if len(names) > 1]
    assert not shared, f"options with the same help text: {shared}"


def test_otgb_help_names_the_commands_lightning_does_not_list():
    """`otgb --help` lists Lightning's subcommands; discover and tune, which otgb adds, are named below them."""
    out = help_text()
    assert "{fit,validate,test,predict}" in out
    assert "otgb discover" in out and "otgb tune" in out and "own --help" in out
