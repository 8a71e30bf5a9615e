"""What the security check costs (issue 41: at most 10 % of a default run and of a paper sweep).

Runs the same ``nirspi-run`` command with and without the check, alternating, in one session, and
prints each call's wall and CPU time (user + system of the child and of what it waited for), the
medians and their ratios:

* **with**: ``nirspi-run ARGS`` as installed: layer 1 (``entry.check_invocation``: the composed
  configuration, Hydra's node included, checked before Hydra; the links among Hydra's files
  removed) and layer 2 (``hydranode.check_job``: the job's Hydra node in the task function, on every
  set the nirspi sweeper composes, in the nirspi launcher);
* **without**: the same command in a child whose ``cli.check_invocation`` only parses the flags
  (no composition, no check), and whose ``check_job`` and link cleanup do nothing. Hydra then gets
  the same arguments.

Each call gets a new output folder (a sweep would otherwise resume from the previous one's
records). Usage::

    python benchmarks/bench_security.py run --repeat 5
    python benchmarks/bench_security.py sweep --repeat 1 -- +experiment=paper 'seed=range(0,2)'

``run`` times ``nirspi-run hydra.run.dir=…`` (the default run); ``sweep`` times ``nirspi-run -m
ARGS hydra.sweep.dir=…``. The numbers in docs/hostile.md come from these two commands.
"""

from __future__ import annotations

import argparse
import os
import resource
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

_WITHOUT = """
import sys
from nirspi_pipe.app import cli, entry, flags, hydranode

def unchecked(args, *, api=False):
    given, overrides = flags.parse_args(list(args))
    return entry.Invocation(
        flags=given,
        overrides=tuple(overrides),
        hydra_argv=(*flags.hydra_flags(given), *overrides),
        config_name=given.get("--config-name") or entry.CONFIG_NAME,
        config=None,
    )

cli.check_invocation = unchecked
cli.check_job = lambda *a, **k: None
hydranode.check_job = lambda *a, **k: None
cli._hydra_files_without_links = lambda *a, **k: None
cli.run(sys.argv[1:])
"""

_WITH = "import sys\nfrom nirspi_pipe.app import cli\ncli.run(sys.argv[1:])\n"


def _cpu() -> float:
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def _one(code: str, args: list[str], env: dict[str, str]) -> tuple[float, float]:
    """Wall and CPU seconds (user + system of the child and of the processes it waited for)."""
    t0, c0 = time.perf_counter(), _cpu()
    res = subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True, env=env)
    wall, cpu = time.perf_counter() - t0, _cpu() - c0
    if res.returncode != 0:
        raise SystemExit(f"bench_security: {' '.join(args)} exited {res.returncode}: {res.stderr.strip()[-500:]}")
    return wall, cpu


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("what", choices=("run", "sweep"))
    parser.add_argument("--repeat", type=int, default=3, help="calls of each variant (alternating)")
    parser.add_argument("--dir", default=None, help="where the output folders go (default: a temporary folder)")
    argv = list(sys.argv[1:] if argv is None else argv)
    extra = argv[argv.index("--") + 1 :] if "--" in argv else []
    opts = parser.parse_args(argv[: argv.index("--")] if "--" in argv else argv)
    opts.args = extra  # the nirspi-run overrides, after --
    if opts.repeat < 1:
        parser.error("--repeat must be >= 1")
    root = Path(opts.dir or tempfile.mkdtemp(prefix="bench_security_"))
    env = {**os.environ, "MPLBACKEND": "Agg"}
    times: dict[str, list[float]] = {"with": [], "without": []}
    cpus: dict[str, list[float]] = {"with": [], "without": []}
    for i in range(opts.repeat):
        for name, code in (
            (("with", _WITH), ("without", _WITHOUT))
            if i % 2 == 0
            else (
                ("without", _WITHOUT),
                ("with", _WITH),
            )
        ):
            out = root / f"{name}_{i}"
            if opts.what == "run":
                args = [*opts.args, f"hydra.run.dir={out}"]
            else:
                args = ["-m", *opts.args, f"hydra.sweep.dir={out}"]
            wall, cpu = _one(code, args, env)
            times[name].append(wall)
            cpus[name].append(cpu)
            print(f"{name:8s} {wall:8.2f} s wall {cpu:8.2f} s CPU  nirspi-run {' '.join(args)}", flush=True)
            shutil.rmtree(out, ignore_errors=True)
    for label, values in (("wall", times), ("CPU", cpus)):
        with_s, without_s = statistics.median(values["with"]), statistics.median(values["without"])
        print(
            f"median {label} with the check {with_s:.2f} s, without {without_s:.2f} s: "
            f"ratio {with_s / without_s:.3f} ({100 * (with_s / without_s - 1):+.1f} %)"
        )
    print(f"load average {os.getloadavg()[0]:.1f}, {opts.repeat} calls of each")
    if opts.dir is None:
        shutil.rmtree(root, ignore_errors=True)


if __name__ == "__main__":
    main()
