"""Command-line flags of ``nirspi-run`` (issue 32): every flag is matched exactly against
:data:`FLAGS` before anything else. Anything that starts with ``-`` and is not spelled exactly as
there (an abbreviation argparse would expand, ``--experimental-rerun``, ``--run``, ``--``) is
refused with one line; Hydra then gets the canonical spelling (``--cfg=job``, :func:`hydra_flags`),
so argparse has nothing left to expand. :class:`Refused` is the entry check's one-line refusal
(:mod:`nirspi_pipe.app.entry`).
"""

from __future__ import annotations

import re
from typing import Any

__all__ = ["FLAGS", "REFUSED_FLAGS", "Refused", "hydra_flags", "parse_args"]


class Refused(ValueError):
    """An invocation the entry check refuses; the message is one line naming the flag or key."""


#: Every flag ``nirspi-run`` accepts, exactly as spelled: ``{spelling: (canonical, value)}``;
#: ``value`` is None (a switch), ``"any"`` (one value), a tuple of allowed values, or
#: ``("?", choices)`` (an optional value, ``--info``). ``--version`` and ``--plugins`` are ours.
FLAGS: dict[str, tuple[str, Any]] = {
    "-h": ("--help", None),
    "--help": ("--help", None),
    "--hydra-help": ("--hydra-help", None),
    "--version": ("--version", None),
    "--plugins": ("--plugins", None),
    "-c": ("--cfg", ("job", "hydra", "all")),
    "--cfg": ("--cfg", ("job", "hydra", "all")),
    "--resolve": ("--resolve", None),
    "-p": ("--package", "any"),
    "--package": ("--package", "any"),
    "-m": ("--multirun", None),
    "--multirun": ("--multirun", None),
    "-i": ("--info", ("?", ("all", "config", "defaults", "defaults-tree", "plugins", "searchpath"))),
    "--info": ("--info", ("?", ("all", "config", "defaults", "defaults-tree", "plugins", "searchpath"))),
    "-sc": ("--shell-completion", None),
    "--shell-completion": ("--shell-completion", None),
    "-cd": ("--config-dir", "any"),
    "--config-dir": ("--config-dir", "any"),
    "-cn": ("--config-name", "any"),
    "--config-name": ("--config-name", "any"),
}
#: Hydra flags that are refused, with the reason.
REFUSED_FLAGS: dict[str, str] = {
    "--experimental-rerun": "it unpickles a file, and unpickling runs code",
    "-cp": "use -cd/--config-dir (added to the search path) instead",
    "--config-path": "use -cd/--config-dir (added to the search path) instead",
    "-r": "a run is what nirspi-run does without a flag; leave it out",
    "--run": "a run is what nirspi-run does without a flag; leave it out",
}
#: Flags that select what Hydra does; at most one.
_COMMANDS = ("--multirun", "--cfg", "--shell-completion", "--info")
CONFIG_NAME_PATTERN = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_.-]*(/[A-Za-z0-9_][A-Za-z0-9_.-]*)*$")
PACKAGE_PATTERN = re.compile(r"^[A-Za-z0-9_]+(\.[A-Za-z0-9_]+)*$")


def parse_args(args: list[str]) -> tuple[dict[str, str | None], list[str]]:
    """Split ``args`` into canonical flags and overrides; :class:`Refused` for any flag not
    spelled exactly as in :data:`FLAGS`, a flag given twice, or a missing/wrong flag value."""
    flags: dict[str, str | None] = {}
    overrides: list[str] = []
    i = 0
    while i < len(args):
        arg = args[i]
        i += 1
        if not arg.startswith("-"):
            overrides.append(arg)
            continue
        spelled, eq, inline = arg.partition("=")
        canonical, kind = _known_flag(spelled, arg)
        if canonical in flags:
            raise Refused(f"{spelled} is given twice; allowed: once")
        flags[canonical], i = _flag_value(spelled, kind, inline if eq else None, args, i)
    _check_flag_combination(flags)
    return flags, overrides


def _known_flag(spelled: str, arg: str) -> tuple[str, Any]:
    """``(canonical name, value kind)`` of a flag spelled exactly as in :data:`FLAGS`, or
    :class:`Refused`."""
    if spelled in REFUSED_FLAGS:
        raise Refused(f"{spelled} is not allowed: {REFUSED_FLAGS[spelled]}")
    if spelled not in FLAGS:
        raise Refused(
            f"{arg[:60]!r} is not a flag nirspi-run accepts (flags are matched exactly, no abbreviations); "
            f"allowed: {', '.join(sorted(FLAGS))}"
        )
    return FLAGS[spelled]


def _flag_value(spelled: str, kind: Any, inline: str | None, args: list[str], i: int) -> tuple[str | None, int]:
    """The value of flag ``spelled`` (``inline``: after ``=``; else ``args[i]`` when the kind takes
    it) and the position after it; :class:`Refused` for a value it does not allow."""
    if kind is None:  # a switch
        if inline is not None:
            raise Refused(f"{spelled} takes no value; allowed: {spelled} alone")
        return None, i
    if isinstance(kind, tuple) and kind and kind[0] == "?":  # an optional value among choices
        choices = kind[1]
        if inline is not None:
            value = inline
        elif i < len(args) and args[i] in choices:
            value, i = args[i], i + 1
        else:
            value = choices[0]
        if value not in choices:
            raise Refused(f"{spelled}={value!r} is not allowed; allowed: {', '.join(choices)}")
        return value, i
    if inline is not None:  # a required value (free, or among the choices of ``kind``)
        value = inline
    elif i < len(args) and not args[i].startswith("-"):
        value, i = args[i], i + 1
    else:
        raise Refused(f"{spelled} needs a value; allowed: {spelled} VALUE")
    if isinstance(kind, tuple) and value not in kind:
        raise Refused(f"{spelled}={value!r} is not allowed; allowed: {', '.join(kind)}")
    return value, i


def _check_flag_combination(flags: dict[str, str | None]) -> None:
    """:class:`Refused` for flags that cannot go together or a malformed package or config name."""
    commands = [c for c in _COMMANDS if c in flags]
    if len(commands) > 1:
        raise Refused(f"{' and '.join(commands)} cannot be combined; allowed: one of {', '.join(_COMMANDS)}")
    if "--resolve" in flags and not ({"--cfg", "--help"} & set(flags)):
        raise Refused("--resolve is only allowed with --cfg or --help")
    if "--package" in flags and not PACKAGE_PATTERN.match(str(flags["--package"])):
        raise Refused(f"--package={flags['--package']!r} is not allowed; allowed: a dotted key path (scene, hydra.run)")
    name = flags.get("--config-name")
    if name is not None and (not CONFIG_NAME_PATTERN.match(name) or ".." in name.split("/")):
        raise Refused(f"--config-name={name!r} is not allowed; allowed: a config name (letters, digits, _ . -)")


def hydra_flags(flags: dict[str, str | None]) -> list[str]:
    """The flags handed on to Hydra, canonical (``--version`` and ``--plugins`` are ours)."""
    return [
        canonical if value is None else f"{canonical}={value}"
        for canonical, value in flags.items()
        if canonical not in ("--version", "--plugins")
    ]
