"""numba's on-disk cache of the compiled mesh kernels: a private folder, and a corrupt cache rebuilt.

numba keeps compiled code in index files (``*.nbi``) that it **unpickles**, and in data files
(``*.nbc``) it loads as machine code. Whoever can write the cache folder can therefore run code
in every process that loads it: a writable cache folder is trusted code (docs/hostile.md). So
the kernels of :mod:`nirspi_pipe.mesh.halfedges`, :mod:`~nirspi_pipe.mesh.meshclean`, :mod:`~nirspi_pipe.mesh.edgeflip`,
:mod:`~nirspi_pipe.mesh.isotropic` and :mod:`~nirspi_pipe.mesh.crustfaces` are cached
in a folder of their own, ``$XDG_CACHE_HOME/nirspi-pipe/numba`` (``~/.cache/nirspi-pipe/numba``),
created private (mode 0700). Were that folder open to others (group or world permissions), it is
closed to 0700 and the kernels' cache files in it are removed (they may have been written by
someone else); a folder another user owns, or a link, is not used: the kernels are cached in a
new private temporary folder instead, with a warning.
``NUMBA_CACHE_DIR``, when the user sets it, is the user's choice and is used as it is.

A cache that does not load (a truncated or garbled index: numba raises while unpickling it) is
rebuilt: :func:`rebuild_on_failure` removes the kernels' cache files, warns naming the folder,
and compiles again once.

Compiling the kernels takes a minute or two (90 s and 118 s of set-up in the first 3D run on a
cold cache, 2 shared cores at load 4 and 8); later runs load them from the cache (0.6 s at load 8).
So a warm-up that compiles says so on stderr (:func:`compile_report`): one line when numba
starts compiling, a progress line every :data:`PROGRESS_EVERY_S` seconds, and one line when it
is done. ``python -m nirspi_pipe.mesh.warmup`` compiles them ahead of the first run.
"""

from __future__ import annotations

import os
import stat
import sys
import tempfile
import time
import warnings
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from functools import lru_cache
from pathlib import Path
from typing import IO, Any, TypeVar

__all__ = ["cache_folder", "compile_report", "prepare", "clear", "rebuild_on_failure"]

#: Seconds between two progress lines while numba compiles (assumed: often enough to show the
#: run is alive, rarely enough that a 90 s compilation prints about ten lines).
PROGRESS_EVERY_S = 10.0

T = TypeVar("T")

#: The modules whose kernels are cached here (numba names their files ``<module>.<function>-…``).
KERNEL_MODULES = ("halfedges", "meshclean", "edgeflip", "isotropic", "crustfaces")


def _default_folder() -> Path:
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "nirspi-pipe" / "numba"


def _private(folder: Path) -> bool:
    """Create ``folder`` (mode 0700) or accept it when it is ours and nobody else may write it;
    a folder of ours with looser permissions is tightened to 0700."""
    try:
        folder.mkdir(parents=True, exist_ok=True, mode=0o700)
        st = folder.lstat()
        if stat.S_ISLNK(st.st_mode) or not stat.S_ISDIR(st.st_mode) or st.st_uid != os.getuid():
            return False
        if st.st_mode & 0o077:  # others could write: close it, and drop what they may have put there
            folder.chmod(0o700)
            for path in folder.rglob("*"):
                if path.suffix in (".nbi", ".nbc"):
                    path.unlink(missing_ok=True)
        return True
    except OSError:
        return False


@lru_cache(maxsize=1)
def prepare() -> Path | None:
    """Point numba's cache at :func:`cache_folder`'s folder (once per process, before the kernels
    are decorated). Returns the folder, or None when numba is not installed."""
    try:
        import numba  # start-up: loads scipy, numba, yaml (282 ms here)
    except ImportError:  # pragma: no cover - numba ships with miepython
        return None
    user = os.environ.get("NUMBA_CACHE_DIR")
    if user:
        return Path(user)
    folder = _default_folder()
    if not _private(folder):
        fallback = Path(tempfile.mkdtemp(prefix="nirspi-numba-"))  # mkdtemp: mode 0700
        warnings.warn(
            f"numba cache {folder} is not a private folder of this user (it may hold others' code); "
            f"compiled kernels are cached in {fallback} for this process",
            stacklevel=2,
        )
        folder = fallback
    numba.config.CACHE_DIR = str(folder)  # type: ignore[attr-defined]  # read when a cached function is decorated
    return folder


def cache_folder() -> Path | None:
    """The folder numba caches the mesh kernels in (None without numba)."""
    return prepare()


def clear(modules: tuple[str, ...] = KERNEL_MODULES) -> list[Path]:
    """Remove the cache files (``*.nbi``, ``*.nbc``) of ``modules``' kernels; returns them."""
    folder = prepare()
    if folder is None or not folder.is_dir():
        return []
    removed = []
    for path in folder.rglob("*"):
        if path.suffix in (".nbi", ".nbc") and path.name.split(".", 1)[0] in modules:
            try:
                path.unlink()
                removed.append(path)
            except OSError:
                pass
    return removed


@contextmanager
def compile_report(
    what: str, modules: tuple[str, ...] = KERNEL_MODULES, stream: IO[str] | None = None
) -> Iterator[None]:
    """While the body runs, say on ``stream`` (default: stderr) when numba compiles one of this
    project's kernels (a cache miss; loading from the cache is silent): a line when the first
    starts, then how many are done every :data:`PROGRESS_EVERY_S` s, and the count and seconds
    at the end. Only kernels defined in ``modules`` (last name of their module) count; one kernel
    compiled for two argument types counts twice (numba compiles each: no total is known ahead)."""
    try:
        # start-up: numba's event API, loaded with numba (jitcache.prepare)
        from numba.core import event
    except ImportError:  # pragma: no cover - numba ships with miepython
        yield
        return
    out = stream if stream is not None else sys.stderr
    state = {"started": 0.0, "last": 0.0, "done": 0}

    def say(line: str) -> None:
        try:
            print(f"numba: {line}", file=out, flush=True)
        except (OSError, ValueError):  # a closed or broken stderr must not fail the run
            pass

    def ours(ev: Any) -> bool:
        module = getattr(getattr(ev.data["dispatcher"], "py_func", None), "__module__", None) or ""
        return module.rsplit(".", 1)[-1] in modules

    class _Report(event.Listener):
        def on_start(self, ev: Any) -> None:
            if ours(ev) and not state["started"]:
                state["started"] = state["last"] = time.monotonic()
                say(
                    f"compiling {what} (not in its cache yet: the first run after an install or upgrade; "
                    f"a minute or two, once: cached in {prepare()}, later runs load them) ..."
                )

        def on_end(self, ev: Any) -> None:
            if not ours(ev):
                return
            state["done"] += 1
            now = time.monotonic()
            if now - state["last"] >= PROGRESS_EVERY_S:
                state["last"] = now
                say(f"{what}: {state['done']} kernels compiled, {now - state['started']:.0f} s")

    with event.install_listener("numba:compile", _Report()):
        yield
    if state["started"]:
        say(f"{what}: {state['done']} kernels compiled in {time.monotonic() - state['started']:.1f} s")


def rebuild_on_failure(
    fn: Callable[[], T],
    modules: tuple[str, ...] = KERNEL_MODULES,
    what: str = "the mesh kernels",
    kernels: tuple[str, ...] | None = None,
) -> T:
    """``fn()`` (a warm-up that compiles or loads the kernels), with numba's compilations of the
    kernels of ``kernels`` (default: ``modules``) reported on stderr (:func:`compile_report`,
    ``what`` names them); when it raises, the cache of ``modules`` is taken
    to be corrupt: its files are removed, a warning names the folder, and ``fn()`` runs once more
    (compiling afresh). A second failure propagates."""
    try:
        with compile_report(what, kernels or modules):
            return fn()
    except Exception as exc:  # numba raises whatever unpickling a bad index raises
        removed = clear(modules)
        if not removed:
            raise
        warnings.warn(
            f"numba cache {prepare()} did not load ({type(exc).__name__}: {str(exc)[:120]}); "
            f"removed {len(removed)} cache files and compiled the kernels again",
            stacklevel=2,
        )
        with compile_report(what, kernels or modules):
            return fn()


def jit(fn: Any, **options: Any) -> Any:
    """``numba.njit(cache=True, nogil=True, **options)(fn)`` with the cache in the private folder
    (:func:`prepare`); ``fn`` itself when numba is missing."""
    if prepare() is None:  # pragma: no cover - numba ships with miepython
        return fn
    from numba import njit  # start-up: loads scipy and numba (1147 ms here)

    return njit(cache=True, nogil=True, **options)(fn)
