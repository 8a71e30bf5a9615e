"""Collect run records into one tidy pandas table (one row per job).

Columns, grouped by prefix:

* identity: ``job`` (folder relative to the sweep), ``status``, ``error``, ``config_hash``,
  ``seed``, ``git_sha``, ``code`` (``git:<sha>`` or ``src:<hash of the package's files>``);
* choices: one column per config group, named after the group (``scene``, ``scan``, …);
* parameters: one column per overridden key (``scene.distance_mm``, ``seed``, …), typed, read
  from each job's resolved config;
* ``metrics.<name>``, ``timings_ms.<stage>``, ``derived.<name>``, ``info.<stage>.<name>``.

Failed jobs are rows with ``status == "failed"`` and their ``error``; they are never dropped.
"""

from __future__ import annotations

import io
import json
import logging
import os
import sys
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from omegaconf import DictConfig, ListConfig, OmegaConf

from nirspi_pipe.app.objective import ObjectiveError, directions_of, objective_names, objective_values, pareto_mask
from nirspi_pipe.app.registration import register_hydra_plugins
from nirspi_pipe.app.sweeper import launcher_failures
from nirspi_pipe.app.sweepfile import SweepFileError, load_sweep_file
from nirspi_pipe.app.tablejobs import build_parts
from nirspi_pipe.finite import drop_nonfinite
from nirspi_pipe.outputfiles import OutputError, atomic_write, drop_links, refuse_link
from nirspi_pipe.records import RECORD_NAME, read_record
from nirspi_pipe.report import write_report
from nirspi_pipe.safeio import read_regular, sanitize_text
from nirspi_pipe.strictjson import decode_nonfinite, dumps_strict
from nirspi_pipe.tables import build_table

__all__ = ["find_records", "records_to_frame", "collect", "CollectResults", "override_keys"]

log = logging.getLogger(__name__)

_SKIP_PREFIXES = ("hydra.", "hydra/")
#: Columns every row has (records_to_frame): an override of the same key (``seed=3``, ``tables=[]``)
#: is already one of them and must not replace it with the config's text (``"[]"`` is no table name).
_IDENTITY = ("job", "status", "error", "config_hash", "seed", "git_sha", "code", "tables")


def find_records(sweep_dir: Path) -> list[Path]:
    """All ``record.json`` files below ``sweep_dir``, in job order (numeric folders first)."""

    def key(p: Path) -> tuple:
        rel = p.parent.relative_to(sweep_dir).parts
        return tuple((0, int(s), "") if s.isdigit() else (1, 0, s) for s in rel)

    return sorted(Path(sweep_dir).rglob(RECORD_NAME), key=key)


def override_keys(overrides: Iterable[str]) -> list[str]:
    """Config keys named by Hydra override strings (``+scene.x=1`` → ``scene.x``)."""
    keys = []
    for ov in overrides:
        if "=" not in ov:
            continue
        key = ov.split("=", 1)[0].lstrip("+~")
        if key and not key.startswith(_SKIP_PREFIXES):
            keys.append(key)
    return keys


def _lookup(config: Mapping[str, Any], dotted: str) -> Any:
    node: Any = config
    for part in dotted.split("."):
        if isinstance(node, Mapping) and part in node:
            node = node[part]
        else:
            return None
    if isinstance(node, (Mapping, list)):
        return str(node)
    return node


def _flatten(prefix: str, mapping: Mapping[str, Any] | None, out: dict[str, Any]) -> None:
    for k, v in (mapping or {}).items():
        name = f"{prefix}.{k}"
        if isinstance(v, Mapping):
            _flatten(name, v, out)
        elif isinstance(v, list):
            out[name] = str(v)
        else:
            out[name] = v


def _uniform(column: pd.Series) -> pd.Series:
    """Make an object column parquet-safe: all numbers → numeric, mixed types → strings."""
    values = column.dropna()
    if len(values) == 0:
        return column
    if values.map(lambda v: isinstance(v, (bool, int, float))).all():
        if values.map(lambda v: isinstance(v, bool)).all():
            return column
        return pd.to_numeric(column)
    return column.map(lambda v: v if v is None or isinstance(v, str) else str(v))


def records_to_frame(records: list[tuple[str, dict[str, Any]]]) -> pd.DataFrame:
    """One row per ``(job, record)``; see the module docstring for the columns."""
    groups: list[str] = []
    params: list[str] = []
    for _, rec in records:
        for g in rec.get("choices", {}):
            if g not in groups:
                groups.append(g)
        for k in override_keys(rec.get("meta", {}).get("overrides", [])):
            if k not in params and k not in groups:
                params.append(k)
    rows = []
    params = [p for p in params if p not in _IDENTITY]  # `tables=[]`, `seed=3`: their own columns
    for job, rec in records:
        meta = rec.get("meta", {})
        row: dict[str, Any] = {
            "job": job,
            "status": meta.get("status"),
            "error": meta.get("error"),
            "config_hash": meta.get("config_hash"),
            "seed": meta.get("seed"),
            "git_sha": meta.get("git_sha"),
            "code": meta.get("code"),
            "tables": ",".join(str(t) for t in (rec.get("config", {}).get("tables") or [])),
        }
        choices = rec.get("choices", {})
        for g in groups:
            row[g] = choices.get(g)
        config = rec.get("config", {})
        for p in params:
            row[p] = decode_nonfinite(_lookup(config, p))  # ".inf" in a record is inf (strictjson.py)
        _flatten("metrics", rec.get("metrics"), row)
        _flatten("timings_ms", rec.get("timings_ms"), row)
        _flatten("derived", rec.get("derived"), row)
        _flatten("info", rec.get("info"), row)
        rows.append(row)
    frame = pd.DataFrame(rows)
    for col in frame.columns:
        if frame[col].dtype == object:
            frame[col] = _uniform(frame[col])
    return frame


def collect(sweep_dir: str | Path, write: bool = True) -> pd.DataFrame:
    """Read every record of a sweep into a frame; write ``results.parquet`` and ``results.csv``
    into the sweep folder when ``write``. Works on complete, partial or killed sweeps.

    With the ``nirspi`` sweeper's ``sweep.json``, the rows are exactly that sweep's jobs, in
    sweep order, and a job without a record (killed, or never started) is a row with
    ``status == "missing"``. Without it, every ``record.json`` below the folder is a row.
    """
    sweep = Path(sweep_dir)
    if not sweep.is_dir():
        raise FileNotFoundError(f"sweep folder {sweep} does not exist")
    info = load_sweep_file(sweep)  # SweepFileError (one line naming it) when malformed
    paths = [sweep / job["key"] / RECORD_NAME for job in info["jobs"]] if info else []
    if not paths:  # no sweep.json, or one listing no jobs: every record below the folder (issue 32)
        paths = find_records(sweep)
        if info and paths:
            print(
                f"nirspi-collect: warning: {sweep}/sweep.json lists no jobs; collected the {len(paths)} "
                "record(s) found below the folder instead",
                file=sys.stderr,
                flush=True,
            )
    records = []
    seen: set[Path] = set()
    for path in paths:
        if path in seen:
            continue
        seen.add(path)
        job = str(path.parent.relative_to(sweep))
        if path.parent.is_symlink():  # never read through a link (docs/hostile.md)
            records.append((job, {"meta": {"status": "failed", "error": "job folder is a symbolic link; refused"}}))
            continue
        try:
            rec = read_record(path)
        except FileNotFoundError:
            records.append((job, {"meta": {"status": "missing", "error": "no record: killed or not run"}}))
        except (OSError, ValueError, RecursionError) as exc:
            log.warning("unreadable record %s: %s", sanitize_text(path, 300), sanitize_text(exc, 300))
            records.append((job, {"meta": {"status": "failed", "error": f"unreadable record: {exc}"}}))
        else:
            # a row with status ok holds no NaN or Inf, whoever wrote the record (issue 41)
            removed = drop_nonfinite(rec) if rec.get("meta", {}).get("status") == "ok" else []
            if removed:
                log.warning("record %s: %s", sanitize_text(path, 300), sanitize_text("; ".join(removed), 300))
            records.append((job, rec))
    frame = records_to_frame(records)
    objective = read_objective(sweep)
    if objective is not None:
        frame = mark_pareto(frame, *objective)
    before = _rows_in(sweep / "results.parquet") if write else None
    if before is not None and before > len(frame):  # never fewer rows without saying so (issue 32)
        print(
            f"nirspi-collect: warning: {sweep / 'results.parquet'} had {before} rows and now gets {len(frame)}: "
            "the records of the missing rows are no longer in the folder",
            file=sys.stderr,
            flush=True,
        )
    if write:  # atomically (unique temporary names): OutputError, one line, when it cannot be written
        buf = io.BytesIO()
        frame.to_parquet(buf, index=False)
        atomic_write(sweep / "results.parquet", buf.getvalue())
        atomic_write(sweep / "results.csv", frame.to_csv(index=False))
    return frame


def _prog() -> str:
    """The command printing: ``nirspi-collect`` when it is the running program, else
    ``nirspi-run`` (issue 34: nirspi-collect printed "nirspi-run: table ...")."""
    name = Path(sys.argv[0]).name if sys.argv and sys.argv[0] else ""
    return name if name == "nirspi-collect" else "nirspi-run"


#: The objective and directions of a sweep (``objective`` and ``hydra.sweeper.direction``),
#: written by :class:`CollectResults` when the sweep starts, read by :func:`collect`.
OBJECTIVE_FILE = "objective.json"
#: The front's picture in the sweep folder (two objectives or more: the first two).
FRONT_PNG = "front.png"


def read_objective(sweep: Path) -> tuple[list[str], list[str]] | None:
    """``(objective names, directions)`` of a sweep from its :data:`OBJECTIVE_FILE`; None when it
    has none or it is unreadable (then no ``pareto`` column)."""
    try:
        info = json.loads(read_regular(Path(sweep) / OBJECTIVE_FILE, 1 << 20))  # never a FIFO
        names = objective_names(info["objective"])
        directions = directions_of(info["direction"], len(names))
    except (OSError, ValueError, KeyError, TypeError, RecursionError, ObjectiveError):
        return None
    return (names, directions) if names and directions else None


def write_objective(sweep: Path, names: list[str], directions: list[str]) -> None:
    atomic_write(Path(sweep) / OBJECTIVE_FILE, dumps_strict({"objective": names, "direction": directions}))


def config_medians(frame: pd.DataFrame, names: list[str]) -> tuple[np.ndarray, np.ndarray]:
    """The ``ok`` rows' objective values aggregated per configuration: ``(values, group)`` where
    ``values`` holds each configuration's median of each objective (rows × objectives) and
    ``group[i]`` is row ``i``'s configuration (-1 for a row that is not ``ok``). Rows with the same
    ``config_hash`` are repeats of one configuration (``hydra.sweeper.repeats``); without that
    column each row is its own."""
    ok = (frame["status"] == "ok").to_numpy()
    values = np.column_stack([pd.to_numeric(frame[n], errors="coerce").to_numpy(dtype=float) for n in names])
    if "config_hash" in frame.columns:
        keys = frame["config_hash"].astype(str).where(frame["config_hash"].notna(), frame["job"].astype(str))
    else:
        keys = pd.Series(np.arange(len(frame)).astype(str))
    group = np.full(len(frame), -1)
    codes, uniques = pd.factorize(keys[ok])
    group[ok] = codes
    medians = np.full((len(uniques), len(names)), np.nan)
    for g in range(len(uniques)):
        with np.errstate(all="ignore"):
            rows = values[group == g]
            # a configuration with a non-finite value in any repeat has no aggregate (never on the front)
            medians[g] = np.median(rows, axis=0) if np.isfinite(rows).all() else np.nan
    return medians, group


def mark_pareto(frame: pd.DataFrame, names: list[str], directions: list[str]) -> pd.DataFrame:
    """``frame`` with a boolean column ``pareto``: the ``ok`` rows of the configurations that no
    other configuration beats in every objective (:func:`nirspi_pipe.app.objective.pareto_mask`),
    each configuration by its median over repeated rows (:func:`config_medians`; one row: its
    value); rows without a value of each objective are False."""
    out = frame.copy()
    out["pareto"] = False
    if not len(out) or any(n not in out.columns for n in names):
        return out
    medians, group = config_medians(out, names)
    on_front = pareto_mask(medians, directions) if len(medians) else np.zeros(0, dtype=bool)
    mask = np.zeros(len(out), dtype=bool)
    mask[group >= 0] = on_front[group[group >= 0]]
    out["pareto"] = mask
    return out


def plot_front(frame: pd.DataFrame, names: list[str], directions: list[str], path: Path) -> Path | None:
    """Draw the first two objectives of every ``ok`` job, the ``pareto`` rows joined as the front,
    into ``path`` (PNG); None when no job has both values. A failing plot is logged, never raised."""
    xi = 1 if names[1].startswith("timings_ms.") and not names[0].startswith("timings_ms.") else 0  # time on x
    x_name, y_name = names[xi], names[1 - xi]
    directions = [directions[xi], directions[1 - xi]]
    ok = frame[frame["status"] == "ok"] if len(frame) else frame
    if not len(ok) or x_name not in ok.columns or y_name not in ok.columns:
        return None
    medians, _group = config_medians(frame, [x_name, y_name])  # one point per configuration
    x, y = medians[:, 0], medians[:, 1]
    keep = np.isfinite(x) & np.isfinite(y)
    if not keep.any():
        return None
    # the front of these two objectives (equal to `pareto` when there are only two)
    front = pareto_mask(np.column_stack([x[keep], y[keep]]), directions[:2])
    try:
        import matplotlib  # start-up: loads matplotlib, PIL, cycler (91 ms here)

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt  # start-up: loads matplotlib, PIL, cycler (332 ms here)

        fig, ax = plt.subplots(figsize=(7.6, 4.4))
        xs, ys = x[keep], y[keep]
        ax.scatter(xs[~front], ys[~front], s=14, color="0.6", label=f"dominated configurations ({(~front).sum()})")
        order = np.argsort(xs[front])
        ax.plot(xs[front][order], ys[front][order], "o-", color="C3", ms=5, lw=1, label=f"Pareto front ({front.sum()})")
        if x_name.startswith("timings_ms") and (xs > 0).all():
            ax.set_xscale("log")
        ax.set_xlabel(f"{x_name} ({directions[0]})")
        ax.set_ylabel(f"{y_name} ({directions[1]})")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0))  # outside: never over a point
        ax.set_title(f"{len(ok)} ok jobs of {len(frame)}: the non-dominated ones joined", fontsize=9)
        fig.tight_layout()
        fig.savefig(path, dpi=120)
        plt.close(fig)
    except Exception as exc:  # noqa: BLE001 - a picture must not cost the results
        log.error("front plot %s failed: %s: %s", path, type(exc).__name__, exc)
        return None
    return path


def _rows_in(path: Path) -> int | None:
    """Rows of an existing parquet file (its metadata only), or None."""
    if not path.is_file() or path.is_symlink():
        return None
    try:
        import pyarrow.parquet as pq  # start-up: loads pyarrow (19 ms here)

        return int(pq.read_metadata(path).num_rows)
    except Exception:  # noqa: BLE001 - an unreadable old table is replaced
        return None


def build_tables(frame: pd.DataFrame, sweep: Path, names: list[str]) -> list[str]:
    """Build each named paper table from ``frame`` into ``sweep/tables``; a table that fails is
    logged and skipped, so it never costs the sweep's other results. Returns those built."""
    folder = sweep / "tables"  # the tables write in place: never through a link (docs/hostile.md)
    try:
        refuse_link(folder, "tables folder")
        if folder.is_dir():
            drop_links(folder, tuple(p.name for p in folder.iterdir() if p.is_symlink()))
    except OutputError as exc:
        print(f"{_prog()}: error: no table built: {exc}", file=sys.stderr, flush=True)
        return []
    built = []
    for name in names:
        try:
            build_table(str(name), frame, sweep / "tables")
            built.append(str(name))
            print(f"{_prog()}: table {name} -> {sweep / 'tables'}")
        except Exception as exc:  # noqa: BLE001 - reported, results kept
            log.error("table %s failed: %s: %s", name, type(exc).__name__, exc)
            print(f"{_prog()}: table {name} FAILED: {type(exc).__name__}: {exc}")
    return built


def tables_by_experiment(frame: pd.DataFrame) -> dict[str, list[str]]:
    """``{experiment: [table, …]}`` from the ``experiment`` and ``tables`` columns of a frame."""
    out: dict[str, list[str]] = {}
    if "tables" not in frame.columns or len(frame) == 0:
        return out
    exp = frame["experiment"] if "experiment" in frame.columns else pd.Series([""] * len(frame))
    for name, tables in zip(exp.fillna(""), frame["tables"].fillna(""), strict=False):
        for t in str(tables).split(","):
            if t and t not in out.setdefault(str(name), []):
                out[str(name)].append(t)
    return out


def finish_sweep(sweep_dir: str | Path, tables: list[str] | None = None) -> pd.DataFrame:
    """Collect a sweep's records, build its paper tables, and write ``report.md`` when it ran
    more than one experiment. ``tables`` overrides the tables the records ask for.

    Each experiment's tables are built from that experiment's rows only."""
    sweep = Path(sweep_dir)
    frame = collect(sweep)
    objective = read_objective(sweep)
    if objective is not None and len(objective[0]) >= 2 and "pareto" in frame.columns:
        path = plot_front(frame, *objective, sweep / FRONT_PNG)
        if path is not None:
            n = int(frame["pareto"].sum())
            print(f"nirspi-run: {n} non-dominated jobs (column pareto) -> {path}")
    built: list[str] = []
    if tables is not None:
        built += build_tables(frame, sweep, tables)
    else:
        parts = []
        for exp, names in tables_by_experiment(frame).items():
            sub = frame[frame["experiment"] == exp] if exp and "experiment" in frame.columns else frame
            parts.append((sub.reset_index(drop=True), names))
        built += build_parts(parts, sweep, build_tables)  # side by side, one experiment a process
    if len(built) > 1:
        path = write_report(sweep, built, frame)
        print(f"{_prog()}: report -> {path}")
    return frame


def unwritable(folder: Path) -> str | None:
    """Why ``folder`` could not be created or written (checked on its nearest existing ancestor,
    nothing is created), or None when it can."""
    probe = Path(folder).absolute()
    while not probe.exists():
        if probe.parent == probe:
            return "no existing parent folder"
        probe = probe.parent
    if not probe.is_dir():
        return f"{probe} is not a folder"
    if not os.access(probe, os.W_OK | os.X_OK):
        return f"{probe} is not writable"
    return None


def _refuse_link(folder: Path, what: str) -> None:
    """One line and exit 1 when ``folder`` is a symbolic link (docs/hostile.md)."""
    try:
        refuse_link(folder, what)
    except OutputError as exc:
        print(f"nirspi-run: error: {exc}", file=sys.stderr, flush=True)
        raise SystemExit(1) from None


def sweep_problem(frame: pd.DataFrame, sweep: Path) -> str | None:
    """Why a finished sweep must exit non-zero, in one line: how many jobs are not ``ok``, by
    status, with their most frequent errors; jobs that failed without a record and without a row
    (:data:`nirspi_pipe.app.jobs.unwritten_jobs`); the launcher's failures
    (:data:`nirspi_pipe.app.sweeper.launcher_failures`). None when every job is ok."""
    from nirspi_pipe.app.jobs import unwritten_jobs  # start-up: loads hydra, hydra_plugins (59 ms here)

    bad = frame[frame["status"] != "ok"] if len(frame) else frame
    rows = set(bad["job"]) if len(bad) else set()
    unseen = [(d, e) for d, e in unwritten_jobs if d.parent != Path(sweep) or d.name not in rows]
    if not len(bad) and not launcher_failures and not unseen:
        return None
    parts = []
    if len(bad):
        listed = ", ".join(f"{v} {k}" for k, v in sorted(bad["status"].value_counts().to_dict().items()))
        errors = bad["error"].fillna("no error recorded").value_counts() if "error" in bad.columns else pd.Series()
        why = "; ".join(f"{n}x {sanitize_text(e, 160)}" for e, n in errors.head(2).items())
        more = f"; {len(errors) - 2} other errors" if len(errors) > 2 else ""
        parts.append(f"{len(bad)} of {len(frame)} jobs did not finish ok ({listed}: {why}{more})")
    if unseen:
        parts.append(f"{len(unseen)} jobs failed without a record ({sanitize_text(unseen[0][1], 200)})")
    if launcher_failures:
        reasons = list(dict.fromkeys(launcher_failures))
        parts.append(f"the launcher failed {len(launcher_failures)} time(s): {'; '.join(reasons)}")
    return "; ".join(parts)


def _plain_job_config(config: Any) -> dict[str, Any]:
    """A job's config without the ``hydra`` node, resolved, as plain data."""
    plain = OmegaConf.to_container(config, resolve=False)
    assert isinstance(plain, dict)
    plain.pop("hydra", None)
    return {str(k): v for k, v in plain.items()}


def sweep_objective(config: Any) -> tuple[list[str], list[str]] | None:
    """``(objective names, directions)`` of a sweep's config (``objective``,
    ``hydra.sweeper.direction``), checked: None when the sweep has no objective. Exits 2 with one
    line when the optimising sweeper has none, or the directions do not fit (before any job runs)."""
    sweeper = config.hydra.sweeper
    optimises = "n_trials" in sweeper  # Optuna's (and any sweeper that asks for trials)
    if optimises and str(sweeper.get("_target_", "")).endswith(".NirspiSweeper"):  # the grid, not NirspiOptunaSweeper
        print(
            "nirspi-run: error: hydra.sweeper.n_trials is set (an Optuna experiment?) but the sweeper is the nirspi "
            "grid; allowed: hydra/sweeper=optuna on the command line (Hydra ignores an experiment's sweeper choice)",
            file=sys.stderr,
            flush=True,
        )
        raise SystemExit(2)
    try:
        names = objective_names(config.get("objective"))
        if optimises and not names:
            raise ObjectiveError(
                f"hydra/sweeper={_sweeper_name(sweeper)} optimises what objective names, and it is not set; "
                "allowed: objective=<record key> or objective=[<key>,<key>], e.g. objective=[metrics.psnr,timings_ms.solver]"
            )
        direction = _plain_value(sweeper.get("direction"))
        if not names and direction is None:
            return None  # no objective: nothing to write or mark
        if names and direction is None:
            return None  # the grid sweeper without directions: values returned, no front marked
        if direction is not None and not names:
            if optimises:
                return None
            raise ObjectiveError(
                "hydra.sweeper.direction is set without objective; allowed: objective=[<key>,…] with it"
            )
        directions = directions_of(direction, len(names))
    except ObjectiveError as exc:
        print(f"nirspi-run: error: {exc}", file=sys.stderr, flush=True)
        raise SystemExit(2) from None
    return names, directions


def _sweeper_name(sweeper: Any) -> str:
    target = str(sweeper.get("_target_", ""))
    return "optuna" if "optuna" in target.lower() else target.rsplit(".", 1)[-1]


def _plain_value(value: Any) -> Any:
    if isinstance(value, (ListConfig, DictConfig)):
        return OmegaConf.to_container(value, resolve=True)
    return value


try:  # the callback base class is Hydra's; keep import errors out of the pure functions above
    from hydra.experimental.callback import Callback
except ImportError:  # pragma: no cover
    Callback = object  # type: ignore[misc,assignment]


class CollectResults(Callback):
    """Hydra callback: after a multirun, write ``results.parquet``/``results.csv`` in the sweep
    folder and log a one-line status count."""

    def on_run_start(self, config: Any, **kwargs: Any) -> None:
        """Before Hydra creates the run folder: one line, not a traceback, when it cannot."""
        try:
            run_dir = Path(str(config.hydra.run.dir))
        except Exception:  # noqa: BLE001 - Hydra will say what is wrong with it
            return
        _refuse_link(run_dir, "output folder (hydra.run.dir)")
        problem = unwritable(run_dir)
        if problem:
            print(f"nirspi-run: error: cannot write {run_dir}: {problem}", file=sys.stderr, flush=True)
            raise SystemExit(1)

    def on_multirun_start(self, config: Any, **kwargs: Any) -> None:
        register_hydra_plugins()
        from nirspi_pipe.app.jobs import unwritten_jobs  # start-up: loads hydra, hydra_plugins (59 ms here)

        unwritten_jobs.clear()  # this sweep's, in this process
        launcher_failures.clear()
        sweep = Path(str(config.hydra.sweep.dir))
        _refuse_link(sweep, "sweep folder (hydra.sweep.dir)")  # before anything is written
        objective = sweep_objective(config)
        if objective is not None:
            write_objective(sweep, *objective)

    def on_job_end(self, config: Any, job_return: Any, **kwargs: Any) -> None:
        """A job run through Hydra's ``run_job`` (launchers other than ``nirspi``: basic, joblib,
        submitit): its return value becomes the values of ``objective`` read from its record
        (:func:`nirspi_pipe.app.objective.objective_values`), what an optimising sweeper reads.
        Without ``objective`` the task function's return stays."""
        if config.get("objective") is None or getattr(job_return, "hydra_cfg", None) is None:
            return

        out_dir = Path(str(job_return.hydra_cfg.hydra.runtime.output_dir))
        try:
            record = read_record(out_dir / RECORD_NAME)
        except (OSError, ValueError):
            record = {"meta": {"status": "failed"}}
        plain = _plain_job_config(config)
        job_return.return_value = objective_values({**record, "config": plain})

    def on_multirun_end(self, config: Any, **kwargs: Any) -> None:
        sweep = Path(config.hydra.sweep.dir)
        if not sweep.is_dir():
            return

        try:
            frame = finish_sweep(sweep)
        except (OutputError, SweepFileError) as exc:  # one line, no traceback
            print(f"nirspi-run: error: {exc}", file=sys.stderr, flush=True)
            raise SystemExit(1) from None
        counts = frame["status"].value_counts().to_dict() if len(frame) else {}
        summary = ", ".join(f"{v} {k}" for k, v in sorted(counts.items())) or "no records"
        print(f"nirspi-run: {len(frame)} jobs ({summary}) -> {sweep / 'results.parquet'}")
        problem = sweep_problem(frame, sweep)
        allow = config.hydra.sweeper.get("allow_failures")  # the nirspi sweeper's; others have none
        rate = config.hydra.sweeper.get("max_failure_rate")  # Optuna's: the share of failed trials it accepts
        hint = "; hydra.sweeper.allow_failures=true exits 0" if allow is not None else ""
        if rate is not None and len(frame):
            allow = float((frame["status"] != "ok").mean()) <= float(rate)
            hint = f"; more than hydra.sweeper.max_failure_rate={rate} of the trials"
        if problem and not allow:
            print(f"nirspi-run: error: {problem}{hint}", file=sys.stderr, flush=True)
            raise SystemExit(1)
