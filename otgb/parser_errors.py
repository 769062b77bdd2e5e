"""The command line's own errors in one line: what, where, the closest valid names, and how to list them.

jsonargparse prints the whole usage (about a hundred lines) before its error; an unknown option
or class is then hard to find. :class:`ConciseParser` replaces that with one line
``otgb <subcommand>: error: ...`` (exit 2); ``--help`` is unchanged.
"""

from __future__ import annotations

import difflib
import importlib
import inspect
import re
import sys
from pathlib import Path
from typing import NoReturn

from jsonargparse import ArgumentParser
from lightning.pytorch.cli import LightningArgumentParser

from otgb.errors import InputError


def closest(name: str, options: list[str], n: int = 3) -> list[str]:
    """The valid names nearest to ``name`` (difflib's ratio), best first."""
    return difflib.get_close_matches(name, options, n=n, cutoff=0.6)


def _did_you_mean(names: list[str]) -> str:
    return f" (did you mean {' or '.join(names)}?)" if names else ""


def option_names(parser: ArgumentParser) -> list[str]:
    """Every option string of ``parser``, nested ones (``--data.simulation_budget``) included."""
    return [s for action in parser._actions for s in action.option_strings if s.startswith("--")]


def _module_and_class(class_path: str) -> tuple[object | None, object | None]:
    module, _, name = class_path.rpartition(".")
    try:
        found = importlib.import_module(module)
    except ImportError:
        return None, None
    return found, getattr(found, name, None)


def class_names(class_path: str) -> list[str]:
    """The classes of the module of a dotted ``class_path`` (empty when the module cannot be imported)."""
    module, _ = _module_and_class(class_path)
    names = [n for n in dir(module) if isinstance(getattr(module, n), type)] if module else []
    return [f"{class_path.rpartition('.')[0]}.{n}" for n in names]


def init_options(class_path: str) -> list[str]:
    """The parameters a class's ``__init__`` accepts."""
    _, cls = _module_and_class(class_path)
    try:
        return [n for n in inspect.signature(cls).parameters if n not in ("self", "args", "kwargs")] if cls else []
    except (TypeError, ValueError):
        return []


def concise(message: str, parser: ArgumentParser) -> tuple[str, bool]:
    """One line for a jsonargparse error ``message`` (what, where, the closest valid names), and whether it is about a
    name (an option, key or class), for which ``--help`` lists the valid ones."""
    keys = re.findall(r'Parser key "([\w.]+)"', message)  # the option, then the keys inside it down to the error
    where = keys[0] if keys else None
    place = "".join(f"{key}: " for key in [f"--{where}", *keys[1:]]) if where else ""
    unknown = re.match(r"unrecognized arguments: (.*)", message)
    if unknown:
        options = [token.split("=")[0] for token in unknown.group(1).split() if token.startswith("--")]
        hints = "".join(_did_you_mean(closest(o, option_names(parser))) for o in options)
        return f"unknown option {' '.join(options) or unknown.group(1)}{hints}", True
    key = re.search(r"(?:Group '([\w.]+)' )?does not accept option '([\w.]+)'", message)
    if key:  # a group's error names the key inside it ('batch_sise' in 'data'): name it in full, as a subcommand's does
        full = ".".join(filter(None, key.groups()))
        names = [o[2:] for o in closest("--" + full, option_names(parser))]
        return f"unknown key '{full}'{_did_you_mean(names)}", True
    option = re.search(r"Option '([\w.]+)' is not accepted", message)
    bad_class = _owner(message, option.start() if option else len(message))
    if bad_class and option:
        name = option.group(1).split(".")[0]  # 'xii.init_args.value': the misspelt option is 'xii'
        return f"{place}{bad_class} has no option '{name}'{_did_you_mean(closest(name, init_options(bad_class)))}", True
    missing = re.search(r"module '([\w.]+)' has no attribute '(\w+)'", message)  # a class given for a callable
    if bad_class or missing:
        path = bad_class or f"{missing.group(1)}.{missing.group(2)}"
        return f"{place}no class '{path}'{_did_you_mean(closest(path, class_names(path)))}", True
    no_file = re.search(r"File does not exist: '([^']+)'", message)
    if no_file:
        path = Path(no_file.group(1))
        siblings = closest(path.name, _names_in(path.parent), n=2)  # beside it, as names
        return f"--{where or 'config'}: no such file {str(path)!r}{_did_you_mean(siblings)}", False
    expected = re.search(r"Expected a <class '(\w+)'>\. Got value: (.*)", message)
    if expected:
        return f"{place}expected {expected.group(1)}, got {expected.group(2).strip()}", False
    lines = [line.strip(" -") for line in message.splitlines() if line.strip(" -")]
    return (f"{place}{lines[-1]}" if where and len(lines) > 1 else "; ".join(lines) or message), False


def _names_in(folder: Path) -> list[str]:
    """The names of the files in ``folder``; none where it cannot be read."""
    try:
        return [entry.name for entry in folder.iterdir() if entry.is_file()]
    except OSError:
        return []


def _owner(message: str, at: int) -> str | None:
    """The class an error at position ``at`` of ``message`` is about: the value a callable was given right after it
    (``Got value: Namespace(class_path='X'``), else the innermost class given before it (``given class_path 'X'``)."""
    value = message[at:].split("Got value: ")[1:2]  # the value the error was raised on, up to the next one
    after = re.search(r"class_path='([\w.]+)'", value[0]) if value and value[0].startswith("Namespace(") else None
    before = re.findall(r"given class_path '([\w.]+)'", message[:at])
    return after.group(1) if after else (before[-1] if before else None)


class ConciseParser(LightningArgumentParser):
    """Lightning's argument parser whose errors are one line naming the closest valid names.

    Abbreviated options are errors too (argparse's default took ``--trainer.max_step`` for
    ``--trainer.max_steps`` without a word, while a misspelling was rejected).
    """

    def __init__(self, *args, raise_input_errors: bool = False, **kwargs) -> None:
        super().__init__(*args, **{"allow_abbrev": False, **kwargs})
        self._given: list[str] = []
        self.raise_input_errors = raise_input_errors  # from Python (MissingEffect): the line as an InputError, no exit

    def parse_args(self, args=None, *rest, **kwargs):
        self._given = list(sys.argv[1:] if args is None else args)  # to name the config file of an error
        return super().parse_args(args, *rest, **kwargs)

    def error(self, message: str, ex: Exception | None = None) -> NoReturn:
        if not self.exit_on_error:
            super().error(message, ex)
        parser = getattr(ex, "subcommand_parser", None) or self
        prog = " ".join(["otgb", *parser.prog.replace(" [options]", "").split()[1:]])
        text, about_names = concise(message, parser)
        where = config_file_with(text, self._given) if about_names else None
        hint = (f" in {where}" if where else "") + (f"; list the options with: {prog} --help" if about_names else "")
        if self.raise_input_errors:
            raise InputError(f"{text}{hint}")
        sys.stderr.write(f"otgb: error: {text}{hint}\n")
        self.exit(2)


def config_file_with(text: str, given: list[str]) -> str | None:
    """The first ``--config`` / ``-c`` file among ``given`` whose YAML holds the name an error ``text`` quotes first (a
    misspelt key's last part or option, as a key; a class, as its path): where a user has to look. None when the
    command line itself holds the name (outside its config files), or no file does."""
    quoted = re.search(r"'([\w.]+)'", text)
    if not quoted:
        return None
    name = quoted.group(1) if "no class" in text else quoted.group(1).rpartition(".")[2]
    pattern = re.escape(name) if "no class" in text else rf"\b{re.escape(name)}\s*:"
    files, others = [], []
    for previous, token in zip(["", *given], given):
        if previous in ("--config", "-c"):
            files.append(token)
        elif token.startswith("--config="):
            files.append(token.removeprefix("--config="))
        elif token not in ("--config", "-c"):
            others.append(token)
    if any(re.search(rf"\b{re.escape(name)}\b", token) for token in others):
        return None
    holding = [f for f in files if Path(f).is_file() and re.search(pattern, Path(f).read_text())]
    return holding[0] if holding else None
