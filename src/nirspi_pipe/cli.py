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
import contextlib
import datetime as _dt
import logging
import os
import sys
import time
import traceback
from pathlib import Path
from typing import Any

from nirspi_pipe.configs import CONFIG_MODULE, CONFIG_NAME
from nirspi_pipe.errors import ConfigError, NirspiError

__all__ = ["run", "collect", "execute_job"]

log = logging.getLogger("nirspi_pipe")

_EXIT_CONFIG = 2
#: Hydra flags after which nothing is built (help, completion, info): no composition is checked.
_NO_RUN_FLAGS = frozenset({"--help", "-h", "--hydra-help", "--version", "-sc", "--shell-completion", "--info", "-i"})


def _one_line(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    first = text[0] if text else type(exc).__name__
    return first if isinstance(exc, NirspiError) else f"{type(exc).__name__}: {first}"


def _summary(record: dict[str, Any], out_dir: Path) -> str:
    from nirspi_pipe.summary import format_summary

    return format_summary(record, out_dir)


def execute_job(
    cfg: Any,
    out_dir: Path,
    choices: dict[str, str],
    overrides: list[str],
    job_num: int | None = None,
    attempt: int | None = None,
    on_output: Any = None,
) -> dict[str, Any]:
    """Run one job (``cfg``: a composed config or its resolved plain dict) and write its record
    and arrays into ``out_dir``. Never raises for a failing
    pipeline: the failure is recorded (``meta.status = "failed"``, ``meta.error``) and the full
    traceback goes to ``error.txt``. Returns the record. Raises
    :class:`nirspi_pipe.records.OutputError` (one line) only when the record cannot be written. ``on_output``, when given, is called
    with the pipeline's ``RunOutput`` of a successful run (the Python API keeps the arrays)."""
    from omegaconf import OmegaConf

    from nirspi_pipe.finite import drop_nonfinite
    from nirspi_pipe.pipeline import run_pipeline
    from nirspi_pipe.records import OutputError, atomic_write, drop_links, new_record, refuse_link, write_record

    refuse_link(out_dir)  # nothing is written through a link (docs/hostile.md)
    config: Any = cfg if isinstance(cfg, dict) else OmegaConf.to_container(cfg, resolve=True)
    started = _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")
    record = new_record(config, choices, overrides, job_num, attempt, seed=_seed_or_none(cfg), started=started)
    t0 = time.perf_counter()
    output = None
    try:
        output = run_pipeline(cfg)
    except Exception as exc:  # noqa: BLE001 - a failed job is data, not a crash
        record["meta"]["error"] = _one_line(exc)
        record["meta"]["warnings"] = list(getattr(exc, "nirspi_warnings", []))
        record["meta"]["error_type"] = "ConfigError" if isinstance(exc, ConfigError) else type(exc).__name__
        try:
            atomic_write(out_dir / "error.txt", traceback.format_exc())
        except OutputError:  # the record below says what failed; it raises if the folder is unwritable
            with contextlib.suppress(OSError):  # an older run's traceback does not belong to this record
                (out_dir / "error.txt").unlink(missing_ok=True)
    else:
        with contextlib.suppress(OSError):  # an older run's traceback does not belong to this record
            (out_dir / "error.txt").unlink(missing_ok=True)
        record.update(
            metrics=output.metrics,
            timings_ms=output.timings_ms,
            derived=output.derived,
            info=output.info,
        )
        record["meta"].update(status="ok", warnings=output.warnings)
        record["meta"]["warnings"] += drop_nonfinite(record)  # no NaN/Inf in an ok record (finite.py)
    record["meta"]["wall_s"] = time.perf_counter() - t0
    if output is not None:
        try:
            drop_links(out_dir, ("summary.png", "mesh.ply", "mesh.png"))  # written in place, not renamed
            _write_products(cfg, out_dir, output)
            if (cfg.get("output", {}) or {}).get("images", True):
                _write_summary_png(out_dir, output, record)
        except OutputError as exc:  # disk full, unwritable folder: the job failed, say where
            record["meta"].update(status="failed", error=str(exc), error_type="OutputError")
        except OSError as exc:  # a writer that does not go through atomic_write (mesh.ply)
            where = f" {exc.filename}" if exc.filename else f" into {out_dir}"
            record["meta"].update(
                status="failed", error=f"cannot write{where}: {exc.strerror or exc}", error_type="OutputError"
            )
        if on_output is not None:
            on_output(output)
    write_record(out_dir, record)
    return record


def _write_products(cfg: Any, out_dir: Path, output: Any) -> None:
    from nirspi_pipe.records import write_arrays

    p = output.products
    truth = p.truth
    out_cfg = cfg.get("output", {}) or {}
    arrays = {
        "reconstruction": p.image.data,
        "upscaled": p.upscaled.data if p.upscaled is not None else None,
        "truth_radiance": truth.radiance if truth is not None else None,
        "truth_depth_m": truth.depth_m if truth is not None else None,
        "truth_mask": truth.mask if truth is not None else None,
        "indices": p.acquisition.indices,
        "y_pos": p.acquisition.y_pos,
        "y_neg": p.acquisition.y_neg,
        "depth_m": p.depth.depth_m if p.depth is not None else None,
    }
    images = {"reconstruction": p.image.data, "truth": truth.radiance if truth is not None else None}
    write_arrays(
        out_dir,
        arrays if out_cfg.get("arrays", True) else {},
        images if out_cfg.get("images", True) else {},
    )
    if p.mesh is not None:
        from nirspi_pipe.mesh.outputs import write_mesh_outputs

        # mesh.ply, and mesh.png (mesh beside the truth) unless output.images is false
        write_mesh_outputs(out_dir, p, render=bool(out_cfg.get("images", True)))


def _write_summary_png(out_dir: Path, output: Any, record: dict[str, Any]) -> None:
    """summary.png (nirspi_pipe.figure); a failing figure is a warning in the record, not a failed run."""
    from nirspi_pipe.figure import write_summary_figure

    try:
        write_summary_figure(out_dir, output.products, record, mesh_png=out_dir / "mesh.png")
    except Exception as exc:  # noqa: BLE001 - a picture must not fail the run
        record["meta"]["warnings"].append(f"summary.png not written: {_one_line(exc)}")


def _seed_or_none(cfg: Any) -> int | None:
    from nirspi_pipe.pipeline import effective_seed

    try:
        return effective_seed(cfg)
    except Exception:  # noqa: BLE001 - an invalid seed is reported by the run itself
        return None


def _hydra_task(cfg: Any) -> None:
    from hydra.core.hydra_config import HydraConfig
    from hydra.types import RunMode

    hc = HydraConfig.get()
    out_dir = Path(hc.runtime.output_dir)
    choices = {k: v for k, v in hc.runtime.choices.items() if not k.startswith("hydra/")}
    overrides = list(hc.overrides.task)
    # hc.job is a DictConfig at run time (typed as the JobConf dataclass); num is '???' in a single run
    job_num: int | None = hc.job.get("num")  # type: ignore[attr-defined]
    from nirspi_pipe.records import OutputError

    if hc.mode == RunMode.MULTIRUN:  # crash-isolated, locked and counted (nirspi_pipe.jobs)
        from nirspi_pipe.jobs import run_sweep_job
        from nirspi_pipe.sweeper import SWEEP_FILE

        sweep_file = Path(str(hc.sweep.dir)) / SWEEP_FILE
        ours = "nirspi" in str(hc.sweeper.get("_target_", ""))  # keyed folders (basic: numbered)
        record = run_sweep_job(
            execute_job,
            cfg,
            out_dir,
            choices,
            overrides,
            job_num=job_num,
            sweep_file=sweep_file if sweep_file.is_file() else None,
            resume=ours and bool(hc.sweeper.get("resume", False)),
        )
    else:
        try:
            record = execute_job(cfg, out_dir, choices, overrides, job_num=job_num)
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
            print(_summary(record, out_dir))
    elif failed:
        log.error("job %s failed: %s", out_dir.name, record["meta"]["error"])


def run(argv: list[str] | None = None) -> None:
    """``nirspi-run``: the Hydra application. Arguments are Hydra's (overrides, ``-m``, …)."""
    import hydra

    from nirspi_pipe.helptext import register_resolvers
    from nirspi_pipe.sweeper import register_hydra_plugins
    from nirspi_pipe.validate import check_config, check_overrides, rewrite_nulls

    args = list(sys.argv[1:] if argv is None else argv)
    if "--version" in args:  # the project's version (Hydra's own flag would print Hydra's)
        from importlib.metadata import version

        from nirspi_pipe import __version__

        print(f"nirspi-pipe {__version__} (hydra-core {version('hydra-core')})")
        return
    if "--plugins" in args:
        _list_plugins()
        return
    _activate_plugins()
    args, problem = rewrite_nulls(args)
    problem = problem or check_overrides(args)
    register_hydra_plugins()
    if not problem and not _NO_RUN_FLAGS.intersection(a.partition("=")[0] for a in args):
        problem = check_config(args)  # YAML, allowed targets, known keys: before Hydra builds anything
    if problem:
        print(f"nirspi-run: error: {problem}", file=sys.stderr)
        raise SystemExit(_EXIT_CONFIG)
    register_resolvers()  # ${nirspi_help:...} in the --help template
    main = hydra.main(version_base="1.3", config_path=f"pkg://{CONFIG_MODULE}", config_name=CONFIG_NAME)(_hydra_task)
    sys.argv = [sys.argv[0], *args]
    main()


def _activate_plugins() -> None:
    """Load installed plugins and put their config folders on Hydra's search path; a plugin
    that fails to load is named in one warning line on stderr and skipped."""
    from nirspi_pipe.plugins import activate

    logging.getLogger("nirspi_pipe.plugins").setLevel(logging.ERROR)  # printed here instead
    for fail in activate().failures:
        print(
            f"nirspi-run: warning: plugin {fail.name!r} ({fail.value}) failed to load and was skipped: {fail.error}",
            file=sys.stderr,
        )


def _list_plugins() -> None:
    """``nirspi-run --plugins``: list installed plugins, the options they add, and failures."""
    from nirspi_pipe.plugins import discover, format_report

    logging.getLogger("nirspi_pipe.plugins").setLevel(logging.ERROR)  # failures are listed below
    print(format_report(discover()))


def collect(argv: list[str] | None = None) -> None:
    """``nirspi-collect DIR``: rebuild ``results.parquet``/``results.csv`` from the records in a
    sweep folder (for sweeps that were killed or are still running)."""
    from nirspi_pipe.results import finish_sweep

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
    from nirspi_pipe.records import OutputError
    from nirspi_pipe.sweeper import SweepFileError

    try:
        frame = finish_sweep(ns.sweep_dir, ns.tables)
    except (FileNotFoundError, SweepFileError) as exc:
        print(f"nirspi-collect: error: {exc}", file=sys.stderr)
        raise SystemExit(2) from None
    except OutputError as exc:  # unwritable sweep folder, disk full
        print(f"nirspi-collect: error: {exc}", file=sys.stderr)
        raise SystemExit(1) from None
    if ns.print_table:
        import pandas as pd

        with pd.option_context("display.width", 160, "display.max_columns", 12):
            print(frame.head(20).to_string(index=False))
    if not ns.quiet:
        counts = frame["status"].value_counts().to_dict() if len(frame) else {}
        by_status = ", ".join(f"{n} {status}" for status, n in sorted(counts.items())) or "none"
        print(f"nirspi-collect: {len(frame)} records ({by_status}) in {ns.sweep_dir}")
        print(
            f"  results: {ns.sweep_dir / 'results.parquet'}, {ns.sweep_dir / 'results.csv'} (--print-table prints them)"
        )
