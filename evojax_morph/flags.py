"""The commands' flags (`run`, `render`, `tame`): their parser class, whose errors exit 2 with
the reason and where the flags are listed, and the flags built from a kind's settings
dataclass (`--agent.FIELD`, `--fitness.FIELD`, `--task.FIELD`)."""

from __future__ import annotations

import argparse
import dataclasses
import inspect
import re


class Parser(argparse.ArgumentParser):
    """An argparse parser whose errors are two lines on stderr and exit 2: the reason, and
    where the flags are listed (argparse's own prints its whole usage block first)."""

    def error(self, message):
        self.exit(2, f"{self.prog}: error: {message}\n{self.prog}: --help lists the flags\n")


def add_settings(group, prefix: str, config: type, skip: tuple[str, ...] = ()) -> None:
    """`--PREFIX.FIELD VALUE` for each field of a kind's settings dataclass `config` (an
    agent's config, a fitness kind's params; or an instance, whose values the help says are
    the defaults: a task's settings) but those in `skip`, typed by its default (a bool as true
    or false), its help what the class says of it (`field_notes`); `given_settings` collects
    the ones given."""
    cls = config if isinstance(config, type) else type(config)  # an instance: its values
    notes = field_notes(cls)
    for f in dataclasses.fields(cls):
        kind = type(f.default)
        if kind not in (bool, int, float, str) or f.name in skip:
            continue
        default = getattr(config, f.name)
        group.add_argument(
            f"--{prefix}.{f.name}", dest=f"{prefix}.{f.name}", default=argparse.SUPPRESS,
            type=boolean if kind is bool else kind, metavar=kind.__name__.upper(),
            help=f"{notes.get(f.name, '')} (its default {default!r})".replace("%", "%%"))


def field_notes(cls: type) -> dict[str, str]:
    """What a dataclass says of each field: its `# comment`, else its docstring's `Attributes:`
    entry (continued lines joined)."""
    doc = inspect.getdoc(cls) or ""
    section = doc.split("\nAttributes:\n", 1)[1] if "\nAttributes:\n" in doc else ""
    notes = {name: " ".join(text.split()) for name, text in
             re.findall(r"^  (\w+): (.*(?:\n    .*)*)", section, re.MULTILINE)}
    return notes | dict(re.findall(r"^\s+(\w+): [^=\n]+=[^#\n]*#\s*(.*)$",
                                   inspect.getsource(cls), re.MULTILINE))


def given_settings(args: argparse.Namespace, prefix: str) -> dict:
    """The `--PREFIX.FIELD` flags of `args` (`add_settings`) given, as {FIELD: value}."""
    return {k.removeprefix(prefix + "."): v for k, v in vars(args).items()
            if k.startswith(prefix + ".")}


def boolean(text: str) -> bool:
    """true or false (any case), as a flag's value."""
    if text.lower() not in ("true", "false"):
        raise argparse.ArgumentTypeError(f"true or false, not {text!r}")
    return text.lower() == "true"
