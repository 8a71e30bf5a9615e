"""Command-line entry points: ``nirspi-run`` (the Hydra app) and ``nirspi-collect``.

``nirspi-run`` runs one configuration, or a sweep with ``-m``. Each job writes ``record.json``,
``arrays.npz`` and PNGs into its own output folder; a sweep also writes ``results.parquet`` and
``results.csv`` into the sweep folder. Errors in the configuration are printed as one line that
names the key and the allowed values, with exit status 2 (set ``NIRSPI_TRACEBACK=1`` to see the
traceback). In a sweep, a failing job is recorded as failed and the others go on.

``nirspi-run --plugins`` lists the installed plugins (entry-point group ``nirspi_pipe.plugins``),
the config options each adds, and those that failed to load (see docs/plugins.md).
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
from importlib.metadata import version
from pathlib import Path
from typing import Any, NoReturn

import hydra
from hydra.core.hydra_config import HydraConfig
from hydra.types import RunMode
from omegaconf import OmegaConf

from nirspi_pipe import __version__
from nirspi_pipe.app.configs import CONFIG_MODULE, CONFIG_NAME
from nirspi_pipe.app.entry import check_invocation
from nirspi_pipe.app.flags import Refused, parse_args
from nirspi_pipe.app.helptext import register_resolvers
from nirspi_pipe.app.hydranode import check_job
from nirspi_pipe.app.plugins import activate, discover, format_report
from nirspi_pipe.app.registration import register_hydra_plugins
from nirspi_pipe.app.sweepfile import SWEEP_FILE, SweepFileError
from nirspi_pipe.errors import ConfigError
from nirspi_pipe.instantiate import Plan
from nirspi_pipe.outputfiles import OutputError, drop_links, refuse_link
from nirspi_pipe.safeio import sanitize_text
from nirspi_pipe.summary import format_summary
from nirspi_pipe.targets import trusted_paths

__all__ = ["run", "collect"]

log = logging.getLogger("nirspi_pipe")

_EXIT_CONFIG = 2


def _hydra_task(cfg: Any) -> None:
    hc = HydraConfig.get()
    try:  # the second gate: the Hydra node this job received, whatever launched it (issue 41)
        check_job(hc)
        # the job's one conversion to plain data, each target checked once: the runner builds
        # from this plan without converting or checking again (issue 42, tests/test_one_plan.py)
        plan = Plan.of(cfg).check()
    except (Refused, ConfigError) as exc:  # a sweep stops here: its other jobs would receive the same node
        print(f"nirspi-run: error: job refused: {exc}", file=sys.stderr)
        raise SystemExit(_EXIT_CONFIG) from None
    out_dir = Path(hc.runtime.output_dir)
    choices = {k: v for k, v in hc.runtime.choices.items() if not k.startswith("hydra/")}
    overrides = [str(o) for o in OmegaConf.to_container(hc.overrides.task, resolve=False) or []]  # as typed
    # hc.job is a DictConfig at run time (typed as the JobConf dataclass); num is '???' in a single run
    job_num: int | None = hc.job.get("num")  # type: ignore[attr-defined]
    from nirspi_pipe.app.jobs import execute_job  # start-up: loads 13 modules of ours (26 ms here)

    if hc.mode == RunMode.MULTIRUN:  # crash-isolated, locked and counted (nirspi_pipe.app.jobs)
        from nirspi_pipe.app.jobs import run_sweep_job  # start-up: loads 13 modules of ours (26 ms here)

        sweep_file = Path(str(hc.sweep.dir)) / SWEEP_FILE
        ours = "nirspi" in str(hc.sweeper.get("_target_", ""))  # keyed folders (basic: numbered)
        record = run_sweep_job(
            execute_job,
            plan,
            out_dir,
            choices,
            overrides,
            job_num=job_num,
            sweep_file=sweep_file if sweep_file.is_file() else None,
            resume=ours and bool(hc.sweeper.get("resume", False)),
        )
    else:
        try:
            record = execute_job(plan, out_dir, choices, overrides, job_num=job_num)
        except OutputError as exc:
            print(f"nirspi-run: error: {exc}", file=sys.stderr)
            raise SystemExit(1) from None
    quiet = bool((cfg.get("output") or {}).get("quiet", False))
    failed = record["meta"]["status"] != "ok"
    if hc.mode == RunMode.RUN:
        if failed:
            config_error = record["meta"].get("error_type") == "ConfigError"
            error_txt = out_dir / "error.txt"  # execute_job leaves one only when it wrote this run's
            written = error_txt.is_file()
            hint = f" (traceback: {error_txt})" if written and not config_error else ""
            print(f"nirspi-run: error: {record['meta']['error']}{hint}", file=sys.stderr)
            if os.environ.get("NIRSPI_TRACEBACK") and written:
                print(error_txt.read_text(), file=sys.stderr)
            raise SystemExit(_EXIT_CONFIG if config_error else 1)
        if not quiet:
            print(format_summary(record, out_dir))
    elif failed:
        log.error("job %s failed: %s", out_dir.name, record["meta"]["error"])


def run(argv: list[str] | None = None) -> None:
    """``nirspi-run``: the Hydra application. Arguments are Hydra's (overrides, ``-m``, …), every
    one checked first (:func:`nirspi_pipe.app.entry.check_invocation`): Hydra gets them only
    when the composed configuration passes."""
    args = list(sys.argv[1:] if argv is None else argv)
    try:
        flags, overrides = parse_args(args)
    except Refused as exc:
        _refuse(exc)
    for alone in ("--version", "--plugins"):  # ours: they print and run nothing, so nothing may go with them
        if alone in flags and (overrides or len(flags) > 1):
            extra = next(iter(overrides), None) or next(f for f in flags if f != alone)
            _refuse(Refused(f"{alone} takes nothing else ({extra[:60]!r} given); allowed: nirspi-run {alone} alone"))
    if "--version" in flags:  # the project's version (Hydra's own flag would print Hydra's)
        print(f"nirspi-pipe {__version__} (hydra-core {version('hydra-core')})")
        return
    if "--plugins" in flags:
        _list_plugins()
        return
    sys.path[:] = trusted_paths()  # nothing is imported from the working directory (plugins, Hydra's scan)
    _activate_plugins()
    register_hydra_plugins()
    try:
        invocation = check_invocation(args)  # the composed config, Hydra's node included, before Hydra
    except Refused as exc:
        _refuse(exc)
    if not {"--cfg", "--help", "--hydra-help", "--info", "--shell-completion"} & set(invocation.flags):
        try:  # Hydra writes its own files before our task runs: no link among them (issue 41)
            _hydra_files_without_links(invocation.config, invocation.multirun)
        except OutputError as exc:
            print(f"nirspi-run: error: {exc}", file=sys.stderr)
            raise SystemExit(1) from None
    register_resolvers()  # ${nirspi_help:...} in the --help template
    main = hydra.main(version_base="1.3", config_path=f"pkg://{CONFIG_MODULE}", config_name=CONFIG_NAME)(_hydra_task)
    sys.argv = [sys.argv[0], *invocation.hydra_argv]
    try:
        main()
    except KeyboardInterrupt:
        print(
            "nirspi-run: interrupted (Ctrl-C); a sweep resumes where it stopped when run again with the same arguments",
            file=sys.stderr,
        )
        raise SystemExit(130) from None


#: What Hydra writes itself in a run or job folder before nirspi-pipe's task runs (with
#: ``hydra.output_subdir`` set): ``.hydra/`` and these files in it, and the job's ``<name>.log``.
_HYDRA_FILES = ("config.yaml", "hydra.yaml", "overrides.yaml")


def _hydra_folder(cfg: Any, multirun: bool, key: str) -> Path | None:
    """The run or sweep folder Hydra will use, or None where it is named only when Hydra starts
    (the clock's default) or by a resolver only a running app has."""
    node = OmegaConf.to_container(cfg.hydra, resolve=False)
    raw = str(((node.get("sweep" if multirun else "run") if isinstance(node, dict) else None) or {}).get("dir"))
    if "${now:" in raw:  # the default: named by the clock when Hydra starts, so a folder made now would be
        return None  # another one (an empty folder left beside the run's, issue 41); a new folder holds no link
    try:
        return Path(str(OmegaConf.select(cfg.hydra, key, throw_on_missing=True)))
    except Exception:  # noqa: BLE001 - a resolver only a running app has: a folder Hydra makes
        return None


def _drop_hydra_links(one: Path) -> None:
    """In ``one``: a ``.hydra`` or ``*.log`` that is a link, and links among ``.hydra``'s files, removed."""
    try:
        names = [e.name for e in os.scandir(one) if e.is_symlink() and (e.name == ".hydra" or e.name.endswith(".log"))]
    except OSError:
        return
    drop_links(one, tuple(names))
    if (one / ".hydra").is_dir():
        drop_links(one / ".hydra", _HYDRA_FILES)


def _hydra_files_without_links(cfg: Any, multirun: bool) -> None:
    """Before Hydra runs: the run folder (``hydra.run.dir``) or the sweep folder
    (``hydra.sweep.dir``) is refused when it is a symbolic link (:class:`OutputError`); in it
    (and, for a sweep, in every folder below it) a ``.hydra`` that is a link, a link among
    ``.hydra``'s files, a ``*.log`` link and a sweep's ``multirun.yaml`` link are removed (the
    link, never its target), so Hydra writes new files there instead of writing through them.
    A link planted *during* the run is not defended (docs/hostile.md)."""
    key = "sweep.dir" if multirun else "run.dir"
    folder = _hydra_folder(cfg, multirun, key)
    if folder is None:
        return
    what = "sweep" if multirun else "output"
    refuse_link(folder, f"{what} folder (hydra.{key})")
    try:  # Hydra creates it first thing, with a traceback when it cannot
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OutputError(
            f"cannot create the {what} folder {sanitize_text(folder, 300)} (hydra.{key}): {exc.strerror or exc}"
        ) from None
    drop_links(folder, ("multirun.yaml",) if multirun else ())
    folders = [Path(d) for d, _, _ in os.walk(folder)] if multirun else [folder]  # os.walk follows no link
    for one in folders:
        _drop_hydra_links(one)


def _refuse(exc: Exception) -> NoReturn:
    print(f"nirspi-run: error: {exc}", file=sys.stderr)
    raise SystemExit(_EXIT_CONFIG)


def _activate_plugins() -> None:
    """Load installed plugins and put their config folders on Hydra's search path; a plugin
    that fails to load is named in one warning line on stderr and skipped."""
    logging.getLogger("nirspi_pipe.plugins").setLevel(logging.ERROR)  # printed here instead
    for fail in activate().failures:
        print(
            f"nirspi-run: warning: plugin {fail.name!r} ({fail.value}) failed to load and was skipped: {fail.error}",
            file=sys.stderr,
        )


def _list_plugins() -> None:
    """``nirspi-run --plugins``: list installed plugins, the options they add, and failures."""
    logging.getLogger("nirspi_pipe.plugins").setLevel(logging.ERROR)  # failures are listed below
    print(format_report(discover()))


def collect(argv: list[str] | None = None) -> None:
    """``nirspi-collect DIR``: rebuild ``results.parquet``/``results.csv`` from the records in a
    sweep folder (for sweeps that were killed or are still running)."""
    from nirspi_pipe.app.results import finish_sweep  # start-up: loads pandas, pyarrow, hydra (358 ms here)

    parser = argparse.ArgumentParser(prog="nirspi-collect", description=collect.__doc__)
    parser.add_argument("sweep_dir", type=Path, help="a multirun folder (hydra.sweep.dir)")
    parser.add_argument("--print-table", action="store_true", help="also print the results table (first 20 rows)")
    parser.add_argument("--quiet", action="store_true", help="print nothing but errors and built tables")
    parser.add_argument(
        "--tables",
        nargs="*",
        default=None,
        metavar="NAME",
        help="paper tables to rebuild (default: those the sweep's experiments list)",
    )
    ns = parser.parse_args(argv)
    try:
        frame = finish_sweep(ns.sweep_dir, ns.tables)
    except (FileNotFoundError, SweepFileError) as exc:
        print(f"nirspi-collect: error: {exc}", file=sys.stderr)
        raise SystemExit(2) from None
    except OutputError as exc:  # unwritable sweep folder, disk full
        print(f"nirspi-collect: error: {exc}", file=sys.stderr)
        raise SystemExit(1) from None
    if ns.print_table:
        import pandas as pd  # start-up: loads pandas, pyarrow, cloudpickle (307 ms here)

        shown = frame.head(20).copy()
        for col in shown.select_dtypes(include="object").columns:  # text from records: no control or bidi characters
            shown[col] = shown[col].map(lambda v: sanitize_text(v, 120) if isinstance(v, str) else v)
        with pd.option_context("display.width", 160, "display.max_columns", 12):
            print(shown.to_string(index=False))
    if not ns.quiet:
        counts = frame["status"].value_counts().to_dict() if len(frame) else {}
        by_status = ", ".join(f"{n} {status}" for status, n in sorted(counts.items())) or "none"
        print(f"nirspi-collect: {len(frame)} records ({by_status}) in {ns.sweep_dir}")
        print(
            f"  results: {ns.sweep_dir / 'results.parquet'}, {ns.sweep_dir / 'results.csv'} (--print-table prints them)"
        )
