"""Where an Optuna study may live: ``hydra.sweeper.storage`` checked (issue 43).

A module of its own, of the standard library only, so that both the job gate
(:mod:`nirspi_pipe.app.hydranode`, its allow-list kind ``storage``) and the study sweeper
(:mod:`nirspi_pipe.app.study`) use one rule without importing each other.
"""

from __future__ import annotations

import os
import re
from pathlib import Path
from typing import Any

__all__ = ["ALLOWED_SCHEMES", "StorageError", "check_storage", "shown_url", "storage_url"]

#: Database URL schemes a study may live in (SQLAlchemy's names, with a driver after ``+``):
#: servers a user names for a shared study, and SQLite inside the sweep folder.
ALLOWED_SCHEMES = ("postgresql", "mysql", "sqlite")
_SCHEME = re.compile(r"^([a-z]+)(\+[a-z0-9_]+)?://")
_STUDY_NAME = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_.=,+-]{0,99}$")
_STORAGE_ALLOWED = (
    "null (SQLite in the sweep folder), sqlite:///<a file inside the sweep folder>, "
    "postgresql://... or mysql://... (a database server)"
)


class StorageError(ValueError):
    """``hydra.sweeper.storage`` (or ``study_name``) is not allowed: one line naming the key."""


def _bad_storage(value: Any, why: str) -> StorageError:
    return StorageError(f"hydra.sweeper.storage={value!r} is not allowed ({why}); allowed: {_STORAGE_ALLOWED}")


def check_storage(value: Any, sweep_dir: str | Path | None = None) -> str | None:
    """Why ``hydra.sweeper.storage`` is refused, or None when it is allowed: null; a
    ``postgresql``/``mysql`` URL; a ``sqlite:///`` file inside ``sweep_dir`` (no ``..``, no
    query, no symbolic link on the way; checked against ``sweep_dir`` when it is given, i.e.
    resolved, by the sweeper). Pure: nothing is opened or created."""
    if value is None:
        return None
    if not isinstance(value, str) or any(ord(c) < 32 for c in value):
        return "not a URL"
    m = _SCHEME.match(value)
    if not m or m.group(1) not in ALLOWED_SCHEMES:
        return "its scheme is not one of " + ", ".join(ALLOWED_SCHEMES)
    if m.group(1) != "sqlite":
        return None
    if not value.startswith("sqlite:///") or "?" in value or "#" in value:
        return "a SQLite URL is sqlite:///<path>, without a query"
    path = value[len("sqlite:///") :]
    if not path or path.endswith("/") or ".." in Path(path).parts or path.startswith(":"):
        return "a SQLite file needs a path without '..'"
    if sweep_dir is None:
        return None
    root = Path(os.path.abspath(sweep_dir))
    target = Path(os.path.abspath(path))
    if target == root or root not in target.parents:
        return f"a SQLite file must be inside the sweep folder {root}"
    probe = target
    while probe != root.parent:
        if probe.is_symlink():
            return f"{probe} is a symbolic link"
        probe = probe.parent
    return None


def storage_url(value: Any, sweep_dir: str | Path, study_name: str) -> str:
    """The database URL of the study: ``value`` checked (:func:`check_storage`), or for null
    ``sqlite:///<absolute sweep folder>/<study_name>.db``. Raises :class:`StorageError`."""
    if not isinstance(study_name, str) or not _STUDY_NAME.match(study_name):
        raise StorageError(
            f"hydra.sweeper.study_name={study_name!r} is not allowed; allowed: letters, digits and _ . = , + - "
            "(at most 100, not starting with '.' or '-'; null: the sweep folder's name)"
        )
    if value is None:
        value = f"sqlite:///{Path(os.path.abspath(sweep_dir)) / (study_name + '.db')}"
    why = check_storage(value, sweep_dir)
    if why is not None:
        raise _bad_storage(value, why)
    return str(value)


def shown_url(url: str) -> str:
    """``url`` with its password hidden, for messages."""
    return re.sub(r"(://[^:/@]+:)[^@/]*@", r"\1***@", url)
