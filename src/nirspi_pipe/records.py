"""Run records: ``record.json`` beside ``arrays.npz`` and PNGs in each job's output folder.

Record format (one JSON object)::

    {"config":    resolved config (no hydra node),
     "choices":   {group: option} from hydra.runtime.choices (hydra/* groups left out),
     "metrics":   {name: float},
     "timings_ms": {stage: float},            # measured by the runner, "total" included
     "derived":   {name: float},              # physical quantities the source used
     "info":      {stage: {name: value}},     # stage bookkeeping (iterations, stop reason)
     "meta":      {"config_hash", "job_key", "inputs": {key: sha256 of the file it names},
                   "seed", "versions", "nirspi_pipe_version", "git_sha", "git_dirty",
                   "source_hash", "code", "platform", "opencl_devices",
                   "status": "ok" | "failed", "error", "error_type", "exit_code", "signal",
                   "attempt", "warnings", "overrides", "job_num", "started", "wall_s"}}

Every file is strict JSON (RFC 8259: no ``NaN``/``Infinity`` tokens; :func:`dumps_strict`). The
result sections never hold a non-finite number (:mod:`nirspi_pipe.finite` leaves them out, each
with its reason); a non-finite number elsewhere, such as the user's ``fog.extent_mm=inf`` in
``config``, is written as the YAML spelling the command line and config files accept: the
strings ``".inf"``, ``"-.inf"`` and ``".nan"`` (:data:`NONFINITE_SPELLINGS`);
:func:`decode_nonfinite` turns them back into floats. :func:`config_hash` hashes the same
encoding, so the hash of a record's ``config`` read back equals the job's.
"""

from __future__ import annotations

import contextlib
import errno
import hashlib
import importlib.util
import io
import json
import math
import os
import platform
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Mapping
from functools import lru_cache
from importlib import metadata
from pathlib import Path
from typing import Any

import numpy as np

from nirspi_pipe import __version__
from nirspi_pipe.errors import NirspiError
from nirspi_pipe.safeio import (
    DEFAULT_BUDGET_BYTES,
    UnsafeInputError,
    open_regular,
    read_budget,
    read_regular,
    sanitize_text,
)

__all__ = [
    "RECORD_NAME",
    "InputHasher",
    "JobLock",
    "OutputError",
    "atomic_write",
    "code_identity",
    "config_hash",
    "decode_nonfinite",
    "dumps_strict",
    "input_files",
    "job_key_of",
    "new_record",
    "provenance",
    "refuse_link",
    "drop_links",
    "read_record",
    "source_hash",
    "write_arrays",
    "pixel_blocks",
    "write_record",
]

RECORD_NAME = "record.json"

_VERSIONED = (
    "nirspi-pipe",
    "numpy",
    "scipy",
    "hydra-core",
    "omegaconf",
    "pandas",
    "scikit-image",
    "miepython",
    "pyopencl",
)


#: How a non-finite float is written in a record (YAML 1.1's spellings, which OmegaConf's loader
#: and ``nirspi-run key=.inf`` read back as floats).
NONFINITE_SPELLINGS = {math.inf: ".inf", -math.inf: "-.inf"}
_NAN_SPELLING = ".nan"
_DECODED = {".inf": math.inf, "-.inf": -math.inf, ".nan": math.nan}


def _float_leaf(x: float) -> float | str:
    if math.isfinite(x):
        return x
    return _NAN_SPELLING if math.isnan(x) else NONFINITE_SPELLINGS[x]


def decode_nonfinite(value: Any) -> Any:
    """``value`` (read from a record) with the spellings ``".inf"``, ``"-.inf"``, ``".nan"``
    turned back into floats, at any depth; anything else unchanged."""
    if isinstance(value, dict):
        return {k: decode_nonfinite(v) for k, v in value.items()}
    if isinstance(value, list):
        return [decode_nonfinite(v) for v in value]
    if isinstance(value, str) and value in _DECODED:
        return _DECODED[value]
    return value


def dumps_strict(value: Any, **kwargs: Any) -> str:
    """``json.dumps`` of ``value`` as strict JSON: numpy values made plain and every non-finite
    float written as its spelling (``".inf"``, module docstring), ``allow_nan=False``; the
    writer for every JSON file the project writes (``kwargs``: ``indent``, ``sort_keys``, ...)."""
    return json.dumps(_jsonable(value), allow_nan=False, **kwargs)


def _jsonable(value: Any) -> Any:
    """Convert numpy scalars/arrays and other leaves into JSON-friendly Python values (a
    non-finite float as its spelling, :data:`NONFINITE_SPELLINGS`)."""
    if isinstance(value, Mapping):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, np.ndarray):
        return _jsonable(value.tolist())
    if isinstance(value, (np.bool_, bool)):
        return bool(value)
    if isinstance(value, np.integer):
        return int(value)
    if isinstance(value, (np.floating, float)):
        return _float_leaf(float(value))
    if value is None or isinstance(value, (str, int)):
        return value
    return str(value)


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
    text = json.dumps(_jsonable(_run_part(config)), sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()[:16]


class OutputError(NirspiError):
    """An output file could not be written (unwritable folder, disk full): one line naming it."""


def _write_failure(path: Path, exc: OSError) -> OutputError:
    reason = exc.strerror or str(exc)
    if exc.errno == errno.ENOSPC:
        reason = "no space left on device"
    return OutputError(f"cannot write {path}: {reason}")


def refuse_link(folder: Path, what: str = "output folder") -> None:
    """Raise :class:`OutputError` (one line naming it and its target) when ``folder`` is a
    symbolic link: nothing is ever written through a link (docs/hostile.md). Only ``folder``
    itself is checked, not the folders above it."""
    folder = Path(folder)
    if folder.is_symlink():
        try:
            target = os.readlink(folder)
        except OSError:
            target = "?"

        raise OutputError(
            f"{what} {sanitize_text(folder, 300)} is a symbolic link (to {sanitize_text(target, 300)}); refused: "
            "nothing is written through links (remove the link, or choose another folder)"
        )


def drop_links(folder: Path, names: tuple[str, ...]) -> None:
    """Remove each file ``folder/name`` that is a symbolic link (the link, never its target), so
    that writers that open the path itself (matplotlib's ``savefig``, pyvista) write a new file
    there, as :func:`atomic_write`'s rename does."""
    for name in names:
        path = Path(folder) / name
        if path.is_symlink():
            try:
                path.unlink()
            except OSError as exc:
                raise _write_failure(path, exc) from None


def atomic_write(path: Path, data: bytes | str) -> Path:
    """Write ``data`` to ``path`` atomically: into a uniquely named temporary file in the same
    folder (``tempfile.mkstemp``), flushed to disk, then renamed over ``path``. Concurrent writers
    never share a temporary file, and readers see the old or the new file, never a torn one.

    Raises :class:`OutputError` (one line naming ``path``) when the folder is unwritable or the
    disk is full; the temporary file is removed, and ``path`` keeps its previous content. A folder
    that is a symbolic link is refused (:func:`refuse_link`); a ``path`` that is one is replaced
    by the rename (the link, never its target).
    """
    path = Path(path)
    refuse_link(path.parent, "folder")
    payload = data.encode() if isinstance(data, str) else bytes(data)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp_name = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    except OSError as exc:
        raise _write_failure(path, exc) from None
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(payload)
            fh.flush()
            os.fsync(fh.fileno())
        os.chmod(tmp_name, 0o644)  # mkstemp makes 0600; records are shared (cluster file systems)
        os.replace(tmp_name, path)
    except BaseException as exc:
        with contextlib.suppress(OSError):
            os.unlink(tmp_name)
        if isinstance(exc, OSError):
            raise _write_failure(path, exc) from None
        raise
    return path


class JobLock:
    """An exclusive lock on a job folder (``.lock``, POSIX ``fcntl.lockf``), so that two sweeps
    writing into one folder never run the same job at once.

    The kernel releases the lock when its holder exits, however it dies (even ``SIGKILL``), so a
    lock is never stale. ``acquire(wait=False)`` returns False when another process holds it;
    ``acquire()`` waits for it. Where ``fcntl`` does not exist (Windows) the lock is a no-op.
    """

    def __init__(self, folder: Path) -> None:
        self.path = Path(folder) / ".lock"
        self._fd: int | None = None

    def acquire(self, wait: bool = True, poll_s: float = 0.2) -> bool:
        try:
            # platform: fcntl is POSIX only
            import fcntl  # POSIX only: this branch does not run on Windows
        except ImportError:  # pragma: no cover - Windows
            return True
        refuse_link(self.path.parent, "job folder")
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            fd = self._open()
        except OSError as exc:  # disk full, unwritable folder: one line naming the lock file
            raise _write_failure(self.path, exc) from None
        while True:
            try:
                fcntl.lockf(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError as exc:
                if exc.errno not in (errno.EACCES, errno.EAGAIN):
                    os.close(fd)
                    raise
                if not wait:
                    os.close(fd)
                    return False
                time.sleep(poll_s)
                continue
            self._fd = fd
            with contextlib.suppress(OSError):
                os.ftruncate(fd, 0)
                os.write(fd, f"{socket.gethostname()} {os.getpid()}\n".encode())
            return True

    def _open(self) -> int:
        """The lock file's descriptor, never through a link: a ``.lock`` that is a symbolic link
        is removed (the link, not its target) and created anew."""
        flags = os.O_RDWR | os.O_CREAT | getattr(os, "O_NOFOLLOW", 0)
        try:
            return os.open(self.path, flags, 0o644)
        except OSError as exc:
            if exc.errno != errno.ELOOP:
                raise
        self.path.unlink()
        return os.open(self.path, flags, 0o644)

    def release(self) -> None:
        if self._fd is not None:
            os.close(self._fd)  # closing the descriptor drops the lock
            self._fd = None


# ---------------------------------------------------------------------------------------------
# Input files: their content is part of a job's key.

_MAX_PATH_TEXT = 4096


def input_files(config: Mapping[str, Any], base: Path | None = None) -> dict[str, Path]:
    """``{dotted.key: path}`` for every string leaf of ``config`` (the ``hydra`` node left out)
    that names an existing regular file, relative paths taken from ``base`` (default: the
    working directory, which Hydra keeps since ``hydra.job.chdir=false``).

    Any key counts, not only ``path``: recordings, meshes, images, weights and whatever a plugin
    reads are all inputs whose content must key the job."""
    base = Path.cwd() if base is None else Path(base)
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
            candidate = Path(node).expanduser()
            candidate = candidate if candidate.is_absolute() else base / candidate
            try:
                if candidate.is_file():
                    found[prefix] = candidate.resolve()
            except OSError:  # a name too long, a permission problem: not an input we can read
                pass

    walk("", config)
    return found


class InputHasher:
    """SHA-256 of input files, cached by ``(path, size, mtime_ns, inode)`` so that a sweep of
    hundreds of jobs naming the same recording reads it once, and a file replaced in place (new
    size or mtime) is read again.

    Bounded (issue 41): a file is opened with :func:`nirspi_pipe.safeio.open_regular` (a FIFO or a
    device swapped in is refused without blocking) and hashed only when its size is within the
    read budget (:func:`nirspi_pipe.safeio.read_budget`: 1 GiB, or ``NIRSPI_READ_BUDGET_MB``),
    the bound every reader of the project applies to what it loads; a larger file (a sparse 16 GB
    file) is not read at all: its entry says so and gives its size, so the time spent hashing is
    at most that of reading the budget once per file. :attr:`bytes_read` counts what was read."""

    def __init__(self, budget: int | None = None) -> None:
        self._cache: dict[tuple[str, int, int, int], str] = {}
        self.budget = budget
        self.bytes_read = 0

    def digest(self, path: Path) -> str:
        """The file's SHA-256 (hex), or ``"not hashed: …"`` naming its size when it is over the
        read budget; :class:`~nirspi_pipe.safeio.UnsafeInputError` when it is not a regular file."""
        with open_regular(path) as fh:
            st = os.fstat(fh.fileno())
            stamp = (str(path), st.st_size, st.st_mtime_ns, st.st_ino)
            if stamp not in self._cache:
                try:
                    limit = read_budget(self.budget)
                except UnsafeInputError:  # a bad NIRSPI_READ_BUDGET_MB: the readers say so in one line
                    limit = DEFAULT_BUDGET_BYTES
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


def job_key_of(config: Mapping[str, Any], inputs: Mapping[str, str]) -> str:
    """A job's folder key: :func:`config_hash` of the resolved config alone when it names no input
    file, else of the config together with the content hashes of its input files, so that
    replacing a recording (same path, new content) gives the job a new key and it reruns."""
    if not inputs:
        return config_hash(config)
    return config_hash({"config": _run_part(config), "inputs": dict(inputs)})


# ---------------------------------------------------------------------------------------------
# Provenance: which code ran.

_GIT_ENV_DROP = (
    "GIT_DIR",
    "GIT_WORK_TREE",
    "GIT_INDEX_FILE",
    "GIT_OBJECT_DIRECTORY",
    "GIT_COMMON_DIR",
    "GIT_CONFIG",
    "GIT_CONFIG_PARAMETERS",
    "GIT_CONFIG_COUNT",
    "GIT_NAMESPACE",
)
_SOURCE_SUFFIXES = (".py", ".yaml", ".yml", ".cl", ".npz", ".json", ".csv", ".md")


def package_root() -> Path:
    """The folder the running ``nirspi_pipe`` package was imported from."""
    return Path(__file__).resolve().parent


def _git(root: Path, args: list[str]) -> str | None:
    """``git -C root args`` with safe options: no fsmonitor hook, no optional locks, no prompt,
    the caller's ``GIT_*`` variables dropped, never searching above ``root``. None on failure."""
    env = {k: v for k, v in os.environ.items() if k not in _GIT_ENV_DROP}
    env.update(GIT_OPTIONAL_LOCKS="0", GIT_TERMINAL_PROMPT="0", GIT_CEILING_DIRECTORIES=str(root.parent))
    cmd = [
        "git",
        "-C",
        str(root),
        "-c",
        "core.fsmonitor=false",
        "-c",
        "core.untrackedCache=false",
        "--no-optional-locks",
        *args,
    ]
    try:
        out = subprocess.run(
            cmd, cwd=root, env=env, capture_output=True, text=True, timeout=10, check=True, stdin=subprocess.DEVNULL
        )
    except (OSError, subprocess.SubprocessError):
        return None
    return out.stdout.strip()


def _checkout_of(pkg: Path) -> Path | None:
    """The git work tree that ``pkg`` is a tracked part of (an editable install), else None.

    Decided from the package's own location only: the nearest folder above it holding ``.git``,
    and only if git tracks the package's ``__init__.py`` there (a copy installed into a venv that
    happens to sit inside some checkout is not tracked, so it does not count)."""
    root = next((p for p in pkg.parents if (p / ".git").exists()), None)
    if root is None:
        return None
    rel = (pkg / "__init__.py").relative_to(root).as_posix()
    if _git(root, ["ls-files", "--error-unmatch", "--", rel]) is None:
        return None
    return root


def _source_roots() -> dict[str, Path]:
    """The folders of the package and of its two data packages (mapped from the repository's
    ``conf/`` and ``experiments/`` in an editable install, nested in a wheel)."""
    roots = {"nirspi_pipe": package_root()}
    for name in ("nirspi_pipe.conf", "nirspi_pipe.experiments"):
        spec = importlib.util.find_spec(name)
        if spec is not None and spec.submodule_search_locations:
            roots[name] = Path(next(iter(spec.submodule_search_locations))).resolve()
    return roots


def source_hash() -> str:
    """SHA-256 (16 hex digits) over the relative paths and contents of the package's source and
    data files (``.py``, configs, experiments, weights), in sorted order: it names the code
    whether it is a checkout or an installed wheel (both give the same hash for the same files)."""
    roots = _source_roots()
    nested = [r for n, r in roots.items() if n != "nirspi_pipe"]
    h = hashlib.sha256()
    for name, root in sorted(roots.items()):
        files = sorted(
            p
            for p in root.rglob("*")
            if p.is_file()
            and p.suffix in _SOURCE_SUFFIXES
            and "__pycache__" not in p.parts
            and (name != "nirspi_pipe" or not any(r in p.parents for r in nested))
        )
        for p in files:
            h.update(f"{name}/{p.relative_to(root).as_posix()}".encode() + b"\0")
            h.update(p.read_bytes() + b"\0")
    return h.hexdigest()[:16]


@lru_cache(maxsize=1)
def code_identity() -> dict[str, Any]:
    """``{"version", "git_sha", "git_dirty", "source_hash", "code"}`` of the running package.

    ``git_sha``/``git_dirty`` only when the package is imported from a git checkout that tracks it
    (git runs with ``-C <that checkout>``, never in the caller's working directory); otherwise
    None. ``source_hash`` always (:func:`source_hash`). ``code`` is the short label reports use:
    ``git:<sha12>[+dirty]`` or ``src:<source_hash>``. Cached per process."""
    pkg = package_root()
    sha = dirty = None
    root = _checkout_of(pkg)
    if root is not None:
        sha = _git(root, ["rev-parse", "HEAD"]) or None
        if sha:
            status = _git(root, ["status", "--porcelain", "--untracked-files=no"])
            dirty = bool(status) if status is not None else None
    src = source_hash()
    code = f"git:{sha[:12]}{'+dirty' if dirty else ''}" if sha else f"src:{src}"
    return {"version": __version__, "git_sha": sha, "git_dirty": dirty, "source_hash": src, "code": code}


def _query_opencl() -> tuple[str, ...]:
    try:
        import pyopencl as cl  # start-up: loads pyopencl (91 ms here); only the provenance of OpenCL runs reads it

        return tuple(f"{p.name} / {d.name}" for p in cl.get_platforms() for d in p.get_devices())
    except Exception as exc:  # noqa: BLE001 - provenance must never fail a run
        return (f"unavailable: {type(exc).__name__}",)


@lru_cache(maxsize=1)
def opencl_devices() -> tuple[str, ...]:
    """``"platform / device"`` names of the OpenCL devices pyopencl sees (empty when none).

    Cached per process: the first call costs the OpenCL platform query (~0.1–0.5 s). Where
    ``os.fork`` exists and this process has not loaded pyopencl yet, the query runs in a forked
    child, so that a sweep worker which forks one child per job (:mod:`nirspi_pipe.app.jobs`) never
    holds an initialised OpenCL runtime, whose threads a fork would not copy.
    """
    if not hasattr(os, "fork") or "pyopencl" in sys.modules:
        return _query_opencl()
    rfd, wfd = os.pipe()
    pid = os.fork()
    if pid == 0:  # pragma: no cover - child
        try:
            os.close(rfd)
            os.write(wfd, json.dumps(list(_query_opencl())).encode())
        finally:
            os._exit(0)
    os.close(wfd)
    with os.fdopen(rfd, "rb") as fh:
        data = fh.read()
    _, status = os.waitpid(pid, 0)
    try:
        return tuple(str(d) for d in json.loads(data.decode()))
    except ValueError:
        return (f"unavailable: query process ended with status {status}",)


@lru_cache(maxsize=1)
def _versions_and_platform() -> tuple[tuple[tuple[str, str | None], ...], str]:
    versions: dict[str, str | None] = {}
    for dist in _VERSIONED:
        try:
            versions[dist] = metadata.version(dist)
        except metadata.PackageNotFoundError:
            versions[dist] = None
    versions["python"] = platform.python_version()
    return tuple(versions.items()), f"{platform.system()}-{platform.machine()} ({platform.platform()})"


def provenance() -> dict[str, Any]:
    """Package versions, platform, OpenCL devices and the code that ran (:func:`code_identity`:
    version, git SHA when imported from its own checkout, and a hash of the source files).
    Computed once per process (16 ms a call otherwise, on every job's record)."""
    versions, where = _versions_and_platform()
    ident = code_identity()
    return {
        "versions": dict(versions),
        "nirspi_pipe_version": ident["version"],
        "git_sha": ident["git_sha"],
        "git_dirty": ident["git_dirty"],
        "source_hash": ident["source_hash"],
        "code": ident["code"],
        "platform": where,
        "opencl_devices": list(opencl_devices()),
    }


def new_record(
    config: dict[str, Any],
    choices: Mapping[str, str],
    overrides: list[str],
    job_num: int | None,
    attempt: int | None,
    **meta: Any,
) -> dict[str, Any]:
    """A job's record before its run: the resolved ``config`` and its keys (config hash; job key
    with the sha256 of every input file the config names), :func:`provenance`, empty results and
    ``status: failed`` until the run says otherwise; ``meta`` adds or overrides fields of ``meta``."""
    inputs = InputHasher().hashes(config)
    return {
        "config": config,
        "choices": dict(choices),
        "metrics": {},
        "timings_ms": {},
        "derived": {},
        "info": {},
        "meta": {
            "config_hash": config_hash(config),
            "job_key": job_key_of(config, inputs),
            "inputs": inputs,
            **provenance(),
            "status": "failed",
            "error": None,
            "warnings": [],
            "overrides": overrides,
            "job_num": job_num,
            "attempt": attempt,
            **meta,
        },
    }


def write_record(folder: Path, record: Mapping[str, Any]) -> Path:
    """Write ``record.json`` atomically (:func:`atomic_write`: a unique temporary file, then a
    rename), so a killed job or a full disk never leaves a half-written record, and two writers
    never tear each other's. Raises :class:`OutputError` when it cannot be written."""
    text = dumps_strict(record, indent=2)
    return atomic_write(Path(folder) / RECORD_NAME, text)


#: The largest ``record.json`` read back (assumed: about a thousand times the 12 kB a default
#: run's record takes, so that no real record is refused and a planted file costs little).
RECORD_READ_LIMIT = 16 << 20


def read_record(path: Path) -> dict[str, Any]:
    """Read one ``record.json`` (``Infinity``/``NaN`` allowed, as written). A file that is not
    regular (a FIFO, a device: refused without blocking), larger than :data:`RECORD_READ_LIMIT`,
    not JSON, nested too deep, or not an object whose ``meta`` (when present) is an object
    raises a ``ValueError`` naming the file (:class:`nirspi_pipe.safeio.UnsafeInputError` for
    the first two), never blocks."""
    raw = read_regular(path, RECORD_READ_LIMIT, str(path))
    try:
        data = json.loads(raw)
    except RecursionError:
        raise ValueError(f"{sanitize_text(path, 300)}: JSON nested too deep; allowed: a record.json") from None
    if not isinstance(data, dict) or not isinstance(data.get("meta", {}), dict):
        shape = type(data).__name__ if not isinstance(data, dict) else "an object whose meta is not an object"
        raise ValueError(f"{sanitize_text(path, 300)}: {shape}, not a record; allowed: a record.json nirspi-run wrote")
    return data


#: The shortest side a written PNG is blown up to, in screen pixels (assumed: 256 px, a size an
#: image viewer shows at 100 % without squinting; an 8 × 8 image becomes 256 × 256).
PNG_MIN_SIDE = 256


def pixel_blocks(image: np.ndarray, min_side: int = PNG_MIN_SIDE) -> np.ndarray:
    """``image`` (2-D) with each pixel repeated into a k × k block, k the smallest integer that
    makes the shorter side at least ``min_side`` (1 for images that large already): the pixel
    grid drawn as it is, nearest neighbour, no interpolation. Values are not changed."""
    a = np.asarray(image)
    short = min(a.shape[:2]) if a.ndim >= 2 and a.size else 0
    k = max(1, -(-int(min_side) // short)) if short else 1
    return np.repeat(np.repeat(a, k, axis=0), k, axis=1) if k > 1 else a


def write_arrays(
    folder: Path, arrays: Mapping[str, np.ndarray | None], images: Mapping[str, np.ndarray | None]
) -> None:
    """Write ``arrays.npz`` (skipping None entries) and 8-bit grayscale PNGs of ``images``, each
    atomically (:func:`atomic_write`); :class:`OutputError` when a file cannot be written. A PNG
    shows each pixel as a square block (:func:`pixel_blocks`: nearest neighbour, no smoothing), so
    that the device's 8 × 8 image is readable; ``arrays.npz`` keeps the arrays themselves."""
    present = {k: np.asarray(v) for k, v in arrays.items() if v is not None}
    if present:
        buf = io.BytesIO()
        np.savez_compressed(buf, **present)  # type: ignore[arg-type]  # numpy stubs type **kwds as allow_pickle
        atomic_write(Path(folder) / "arrays.npz", buf.getvalue())
    if images:
        from matplotlib.image import imsave  # start-up: matplotlib takes ~1 s to import; only the PNGs need it

        for name, img in images.items():
            if img is None:
                continue
            a = np.nan_to_num(np.asarray(img, dtype=np.float64), nan=0.0, posinf=1.0, neginf=0.0)
            buf = io.BytesIO()
            imsave(buf, pixel_blocks(np.clip(a, 0.0, 1.0)), cmap="gray", vmin=0.0, vmax=1.0, format="png")
            atomic_write(Path(folder) / f"{name}.png", buf.getvalue())
