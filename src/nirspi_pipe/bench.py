"""``nirspi-bench NAME [ARGS]``: run a benchmark from :mod:`nirspi_pipe.benchmarks`.

Each benchmark module ``nirspi_pipe.benchmarks.<name>`` has ``main(argv: list[str]) -> int``. A
benchmark always measures a reference in the same process and reports the ratio, because these
machines are shared and noisy: absolute milliseconds alone mean little.
"""

from __future__ import annotations

import importlib
import pkgutil
import sys

__all__ = ["main", "available"]


def available() -> list[str]:
    """Names of the installed benchmarks."""
    import nirspi_pipe.benchmarks as pkg  # start-up: loads numpy (334 ms here)

    return sorted(m.name for m in pkgutil.iter_modules(pkg.__path__) if not m.name.startswith("_"))


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``nirspi-bench``."""
    args = list(sys.argv[1:] if argv is None else argv)
    names = available()
    if not args or args[0] in ("-h", "--help"):
        print("usage: nirspi-bench NAME [ARGS]   (NAME --help for its options)")
        print("benchmarks: " + ", ".join(names))
        return 0 if args else 2
    name = args[0]
    if name not in names:
        print(f"nirspi-bench: error: unknown benchmark {name!r}; allowed: {', '.join(names)}", file=sys.stderr)
        return 2
    module = importlib.import_module(f"nirspi_pipe.benchmarks.{name}")
    return int(module.main(args[1:]) or 0)


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
