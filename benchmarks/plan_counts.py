"""How often one ``nirspi-run`` converts and checks its config (issue 42 item 1: each ``_target_``
checked once, at most 30 allow-list checks, one conversion at the boundary).

Runs ``nirspi-run ARGS`` in this process under ``cProfile`` and prints the call counts that say
it: the runner's allow-list check (``targets.check_target``) and who called it, the import by
string (``targets.locate``), ``instantiate.plain_config`` (all calls, and the outermost ones:
conversions), ``OmegaConf.to_container``, ``instantiate.build`` and ``check_types``. Usage::

    python benchmarks/plan_counts.py hydra.run.dir=/tmp/plan_counts
    python benchmarks/plan_counts.py sfs=second_order itof=cw4 fusion=itof surface=power_crust \\
        metrics=full hydra.run.dir=/tmp/plan_counts_3d

A default run at b69ec9a: 35 allow-list checks (24 for the config's 24 targets, once, and 11 by
the app's schema catalogue reading its targets' signatures), 35 imports by string, 1 outermost
``plain_config``; before the plan (the working tree of 49b7092^ with its own instantiate, pipeline,
execute, app/cli, app/entry and app/validate): 127, 91 and 22. At 9ea4bb5 (16 targets since the
metrics take the built stages): 27 checks (16 + the catalogue's 11), and 39 checks and 8 outermost
``plain_config`` with ``camera.resolution=16`` (the app's type check of the overridden config
checked its targets again and converted each stage node). Since every check goes through
``targets.check_once`` (a string passed against the same allow-list is not compared again: the
catalogue's verdicts serve the plans): 12 checks in both runs, one per distinct target string, and
1 and 2 outermost ``plain_config``.
"""

from __future__ import annotations

import cProfile
import pstats
import sys

from nirspi_pipe.app.cli import run

WATCHED = {
    ("targets.py", "check_target"),
    ("targets.py", "locate"),
    ("hydratargets.py", "check_target"),
    ("instantiate.py", "plain_config"),
    ("instantiate.py", "build"),
    ("instantiate.py", "check_types"),
    ("omegaconf.py", "to_container"),
}


def main(argv: list[str]) -> None:
    profile = cProfile.Profile()
    profile.enable()
    try:
        run(argv)
    except SystemExit as exc:
        print(f"nirspi-run exited with {exc.code}")
    profile.disable()
    stats = pstats.Stats(profile).stats  # type: ignore[attr-defined]
    print(f"{'function':34} {'calls':>6} {'outermost':>9}   callers")
    for (path, _line, name), (primitive, calls, _tt, _ct, callers) in sorted(stats.items(), key=lambda kv: kv[0][2]):
        where = path.rsplit("/", 1)[-1]
        if (where, name) not in WATCHED:
            continue
        by = ", ".join(
            f"{c[0].rsplit('/', 1)[-1]}:{c[2]} {v[0]}" for c, v in sorted(callers.items(), key=lambda kv: -kv[1][0])
        )
        print(f"{where + ':' + name:34} {calls:6d} {primitive:9d}   {by}")


if __name__ == "__main__":
    main(sys.argv[1:])
