"""Compile (or load from numba's cache) every compiled mesh kernel now, ahead of the first 3D run.

    python -m nirspi_pipe.mesh.warmup

The first 3D run after an install otherwise spends a minute or two compiling them (saying so on
stderr, :func:`nirspi_pipe.mesh.jitcache.compile_report`); afterwards they load from the cache
(:mod:`nirspi_pipe.mesh.jitcache`). Exit status 0 when the kernels are ready, 1 when numba could
not compile them (the surface stages then use pymeshlab), 2 on a usage error.
"""

from __future__ import annotations

import sys

from nirspi_pipe.mesh import jitcache, powercrust, remesh

__all__ = ["main"]


def main(argv: list[str] | None = None) -> int:
    """Command line: see the module docstring."""
    args = sys.argv[1:] if argv is None else argv
    if args:
        print(f"usage: python -m nirspi_pipe.mesh.warmup (no arguments; got {' '.join(args)})", file=sys.stderr)
        return 2
    ok = remesh.resolve_remesher("auto") == "compiled" and powercrust.warm_up()
    state = "ready" if ok else "NOT compiled (the surface stages will use pymeshlab)"
    print(f"mesh kernels {state}; numba cache: {jitcache.cache_folder()}")
    return 0 if ok else 1


if __name__ == "__main__":
    raise SystemExit(main())
