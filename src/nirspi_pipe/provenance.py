"""Provenance: which code ran (:func:`code_identity`: version, git SHA when the package is
imported from its own checkout, a hash of the source files), package versions, platform and
OpenCL devices (:func:`provenance`), written into each record's ``meta``. Moved out of
:mod:`nirspi_pipe.records` (issue 42 item 5).
"""

from __future__ import annotations

import hashlib
import importlib.util
import json
import os
import platform
import subprocess
import sys
from functools import lru_cache
from importlib import metadata
from pathlib import Path
from typing import Any

from nirspi_pipe import __version__

__all__ = ["code_identity", "opencl_devices", "package_root", "provenance", "source_hash"]

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
