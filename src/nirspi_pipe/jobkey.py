"""A job's keys: the hash of its resolved config (:func:`config_hash`) and its folder key
(:func:`job_key_of`), which adds the content hashes of the input files the config names
(:func:`input_files`, :class:`InputHasher`). Moved out of :mod:`nirspi_pipe.records` (issue 42 item 5).
"""

from __future__ import annotations

import hashlib
import json
import os
import stat
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from nirspi_pipe.safeio import DEFAULT_BUDGET_BYTES, UnsafeInputError, open_regular, read_budget
from nirspi_pipe.strictjson import jsonable

__all__ = ["NOT_HASHED", "InputHasher", "config_hash", "input_files", "job_key_of"]


#: Top-level config keys that say what reads a job's record, not how the job runs (``objective``:
#: the record keys a sweeper optimises). They are left out of :func:`config_hash`, so setting one
#: neither moves a job to another folder nor changes the seed ``seed: null`` derives.
NOT_HASHED = ("objective",)


def _run_part(config: Mapping[str, Any]) -> Mapping[str, Any]:
    if not any(key in config for key in NOT_HASHED):
        return config
    return {k: v for k, v in config.items() if k not in NOT_HASHED}


def config_hash(config: Mapping[str, Any]) -> str:
    """Deterministic 16-hex-digit key of a resolved config (sha256 of canonical JSON), the keys of
    :data:`NOT_HASHED` left out."""
    text = json.dumps(jsonable(_run_part(config)), sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()[:16]


# Input files: their content is part of a job's key.

_MAX_PATH_TEXT = 4096


def input_files(config: Mapping[str, Any], base: Path | None = None) -> dict[str, Path]:
    """``{dotted.key: path}`` for every string leaf of ``config`` (the ``hydra`` node left out)
    that names an existing regular file, relative paths taken from ``base`` (default: the
    working directory, which Hydra keeps since ``hydra.job.chdir=false``).

    Any key counts, not only ``path``: recordings, meshes, images, weights and whatever a plugin
    reads are all inputs whose content must key the job."""
    base = Path.cwd() if base is None else Path(base)
    base_text = str(base)
    found: dict[str, Path] = {}

    def walk(prefix: str, node: Any) -> None:
        if isinstance(node, Mapping):
            for k, v in node.items():
                if not prefix and k == "hydra":
                    continue
                walk(f"{prefix}.{k}" if prefix else str(k), v)
        elif isinstance(node, (list, tuple)):
            for i, v in enumerate(node):
                walk(f"{prefix}[{i}]", v)
        elif isinstance(node, str) and 0 < len(node) < _MAX_PATH_TEXT and "\n" not in node and "\0" not in node:
            if _POSIX and not _pathlib_differs(node):
                # a plain stat of the text as it is: what Path(...).is_file() asks, without pathlib
                # (2.6 ms of a paper job's 3 ms record, in each job and again in keying)
                try:
                    if not stat.S_ISREG(os.stat(os.path.join(base_text, node)).st_mode):
                        return
                except (OSError, ValueError):  # no such file, a name too long, a permission problem
                    return
            candidate = Path(node).expanduser()
            candidate = candidate if candidate.is_absolute() else base / candidate
            try:
                if candidate.is_file():
                    found[prefix] = candidate.resolve()
            except OSError:  # a name too long, a permission problem: not an input we can read
                pass

    walk("", config)
    return found


_POSIX = os.name == "posix"


def _pathlib_differs(text: str) -> bool:
    """Whether ``pathlib`` reads ``text`` as another file than the operating system would: a
    home folder (``~``), or a trailing ``/`` or ``/.`` that ``Path`` drops (``file.txt/`` is
    ``file.txt`` to ``Path``, no file to ``os.stat``). For the rest, ``os.stat`` of
    ``os.path.join(base, text)`` finds the file ``Path`` finds (``//`` and ``/./`` inside name
    the same file to both), so the fast check only rules files out."""
    return text.startswith("~") or text.endswith("/") or text.endswith("/.") or text == "."


class InputHasher:
    """SHA-256 of input files, cached by ``(path, size, mtime_ns, inode, read budget)`` so that a sweep of
    hundreds of jobs naming the same recording reads it once, and a file replaced in place (new
    size or mtime) is read again.

    Bounded (issue 41): a file is opened with :func:`nirspi_pipe.safeio.open_regular` (a FIFO or a
    device swapped in is refused without blocking) and hashed only when its size is within the
    read budget (:func:`nirspi_pipe.safeio.read_budget`: 1 GiB, or ``NIRSPI_READ_BUDGET_MB``),
    the bound every reader of the project applies to what it loads; a larger file (a sparse 16 GB
    file) is not read at all: its entry says so and gives its size, so the time spent hashing is
    at most that of reading the budget once per file. :attr:`bytes_read` counts what was read."""

    def __init__(self, budget: int | None = None) -> None:
        self._cache: dict[tuple[str, int, int, int, int], str] = {}
        self.budget = budget
        self.bytes_read = 0

    def digest(self, path: Path) -> str:
        """The file's SHA-256 (hex), or ``"not hashed: …"`` naming its size when it is over the
        read budget; :class:`~nirspi_pipe.safeio.UnsafeInputError` when it is not a regular file."""
        with open_regular(path) as fh:
            st = os.fstat(fh.fileno())
            try:
                limit = read_budget(self.budget)
            except UnsafeInputError:  # a bad NIRSPI_READ_BUDGET_MB: the readers say so in one line
                limit = DEFAULT_BUDGET_BYTES
            # the budget too: a process-wide hasher (records.new_record's) sees NIRSPI_READ_BUDGET_MB change
            stamp = (str(path), st.st_size, st.st_mtime_ns, st.st_ino, limit)
            if stamp not in self._cache:
                if st.st_size > limit:
                    self._cache[stamp] = (
                        f"not hashed: {st.st_size} bytes, over the read budget of {limit} bytes (NIRSPI_READ_BUDGET_MB)"
                    )
                else:
                    h = hashlib.sha256()
                    left = limit + 1  # a file growing meanwhile is read no further than the budget
                    while left > 0:
                        block = fh.read(min(1 << 20, left))
                        if not block:
                            break
                        h.update(block)
                        self.bytes_read += len(block)
                        left -= len(block)
                    self._cache[stamp] = h.hexdigest()
        return self._cache[stamp]

    def hashes(self, config: Mapping[str, Any], base: Path | None = None) -> dict[str, str]:
        """``{dotted.key: sha256}`` of every input file ``config`` names (see :func:`input_files`)."""
        out = {}
        for key, path in sorted(input_files(config, base).items()):
            try:
                out[key] = self.digest(path)
            except OSError as exc:  # unreadable: the job will say so; key it by the reason
                out[key] = f"unreadable: {exc.strerror or exc}"
            except UnsafeInputError:  # swapped for a FIFO or a device since input_files looked
                out[key] = "unreadable: not a regular file"
        return out


def job_key_of(config: Mapping[str, Any], inputs: Mapping[str, str], hashed: str | None = None) -> str:
    """A job's folder key: :func:`config_hash` of the resolved config alone when it names no input
    file, else of the config together with the content hashes of its input files, so that
    replacing a recording (same path, new content) gives the job a new key and it reruns.
    ``hashed``: ``config_hash(config)`` when the caller has it already (not computed twice)."""
    if not inputs:
        return config_hash(config) if hashed is None else hashed
    return config_hash({"config": _run_part(config), "inputs": dict(inputs)})
