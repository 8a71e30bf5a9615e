"""Run one job and write what it produced: the runner's entry point for every front end.

``execute_job`` takes a resolved configuration as plain data (``dict``/``list``/scalars, as
:func:`nirspi_pipe.instantiate.plain_config` makes it), runs :func:`nirspi_pipe.pipeline.run_pipeline`
and writes ``record.json``, ``arrays.npz``, PNGs, ``summary.png`` and meshes into the job's
folder. It imports nothing of Hydra or OmegaConf: the command line, the sweep launcher and the
Python API (:mod:`nirspi_pipe.app`) compose the config and call it.
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import json
import time
import traceback
from collections.abc import Iterable, Iterator, Mapping
from pathlib import Path
from typing import Any

from nirspi_pipe import safeio  # noqa: F401 - the records' writers import it on first use: loaded before a fork
from nirspi_pipe.errors import ConfigError, NirspiError
from nirspi_pipe.figure import write_summary_figure
from nirspi_pipe.finite import drop_nonfinite
from nirspi_pipe.instantiate import Plan, plain_config
from nirspi_pipe.mesh.outputs import write_mesh_outputs
from nirspi_pipe.outputfiles import OutputError, atomic_write, drop_links, refuse_link
from nirspi_pipe.pipeline import RunOutput, effective_seed, run_pipeline
from nirspi_pipe.provenance import provenance
from nirspi_pipe.records import new_record, write_arrays, write_record
from nirspi_pipe.stages import ScanIndices, WarmsUp
from nirspi_pipe.targets import allowed_targets, locate

__all__ = ["execute_job", "one_line", "warm_up"]


def one_line(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    first = text[0] if text else type(exc).__name__
    return first if isinstance(exc, NirspiError) else f"{type(exc).__name__}: {first}"


def execute_job(
    cfg: Any,
    out_dir: Path,
    choices: dict[str, str],
    overrides: list[str],
    job_num: int | None = None,
    attempt: int | None = None,
    on_output: Any = None,
    scan_indices: ScanIndices | None = None,
) -> dict[str, Any]:
    """Run one job (``cfg``: the job's :class:`~nirspi_pipe.instantiate.Plan`, made by the front
    end at its boundary; or a resolved config as plain data, or any mapping that reads as one,
    converted here once into a plan) and write its record and arrays into ``out_dir``. Never raises for a failing pipeline: the failure is recorded (``meta.status = "failed"``, ``meta.error``) and the full
    traceback goes to ``error.txt``. Returns the record. Raises
    :class:`nirspi_pipe.outputfiles.OutputError` (one line) only when the record cannot be written. ``on_output``, when given, is called
    with the pipeline's ``RunOutput`` of a successful run (the Python API keeps the arrays).
    ``scan_indices`` resolves the scan option a recording names (see :func:`run_pipeline`)."""
    refuse_link(out_dir)  # nothing is written through a link (docs/hostile.md)
    plan = Plan.of(cfg)  # the one conversion (none when the front end made the plan)
    config = plan.config
    started = _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")
    record = new_record(config, choices, overrides, job_num, attempt, seed=_seed_or_none(config), started=started)
    t0 = time.perf_counter()
    output = None
    try:
        output = run_pipeline(plan, scan_indices=scan_indices)
    except Exception as exc:  # noqa: BLE001 - a failed job is data, not a crash
        record["meta"]["error"] = one_line(exc)
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
        # no NaN/Inf in an ok record, each value left out with its reason (finite.py)
        record["meta"]["warnings"] += drop_nonfinite(record, _image_sides(output))
    record["meta"]["wall_s"] = time.perf_counter() - t0
    if output is not None:
        try:
            drop_links(out_dir, ("summary.png", "mesh.ply", "mesh.png"))  # written in place, not renamed
            _write_products(config, out_dir, output)
            if (config.get("output", {}) or {}).get("images", True):
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


def _write_products(cfg: Mapping[str, Any], out_dir: Path, output: RunOutput) -> None:
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
    images = {
        "reconstruction": p.image.data,
        "upscaled": p.upscaled.data if p.upscaled is not None else None,
        "truth": truth.radiance if truth is not None else None,
    }
    write_arrays(
        out_dir,
        arrays if out_cfg.get("arrays", True) else {},
        images if out_cfg.get("images", True) else {},
    )
    if p.mesh is not None:
        # start-up: loads PIL, charset_normalizer, cycler (454 ms here)
        from nirspi_pipe.mesh.metrics3d import run_depth_truth  # deferred: loads the 3D metrics only for 3D runs

        # mesh.ply, and mesh.png (mesh beside the truth on the grid depth is scored on) unless
        # output.images is false
        render = bool(out_cfg.get("images", True))
        write_mesh_outputs(out_dir, p, render=render, truth=run_depth_truth(p, cfg) if render else None)


def _write_summary_png(out_dir: Path, output: RunOutput, record: dict[str, Any]) -> None:
    """summary.png (nirspi_pipe.figure); a failing figure is a warning in the record, not a failed run."""
    try:
        write_summary_figure(out_dir, output.products, record, mesh_png=out_dir / "mesh.png")
    except Exception as exc:  # noqa: BLE001 - a picture must not fail the run
        record["meta"]["warnings"].append(f"summary.png not written: {one_line(exc)}")


def _image_sides(output: RunOutput) -> dict[str, int]:
    """The sides (pixels) of the images the metrics score, by metric prefix (finite.reason_for):
    ``""`` the camera image; ``upscale``/``bicubic``/``noise`` the upscaled one."""
    p = output.products
    sides = {"": int(min(p.image.data.shape))}
    if p.upscaled is not None:
        up = int(min(p.upscaled.data.shape))
        sides.update(upscale=up, bicubic=up, noise=up)
    return sides


def _seed_or_none(cfg: Mapping[str, Any]) -> int | None:
    try:
        return effective_seed(cfg)
    except Exception:  # noqa: BLE001 - an invalid seed is reported by the run itself
        return None


def _stage_nodes(node: Any) -> Iterator[tuple[str, Mapping[str, Any]]]:
    """``(target, node)`` of every ``_target_`` node in ``node`` (plain data), depth first."""
    if isinstance(node, Mapping):
        target = node.get("_target_")
        if isinstance(target, str):
            yield target, node
        for value in node.values():
            yield from _stage_nodes(value)
    elif isinstance(node, list):
        for value in node:
            yield from _stage_nodes(value)


def warm_up(configs: Iterable[Mapping[str, Any]]) -> list[str]:
    """Prepare this process for the jobs of ``configs`` (resolved plain configs) before it forks
    them: import the runner's own modules and the module of every allowed ``_target_`` the
    configs name, then call the class method ``warm_up(params)`` of each class that has one
    (:class:`nirspi_pipe.stages.WarmsUp`), once per distinct ``(target, params)``. Returns
    what failed, as ``target: error`` lines (the job that needs it reports it in its record);
    a target outside the allow-list is not imported (its job refuses it).

    Each target is imported once, and the parameters of a node are read only when its class
    has the hook (or failed to import): a paper-sized sweep's 2640 configs took 2.9 s here when
    every node's parameters were serialized, in the sweeping process before any job starts."""
    provenance()  # the installation's identity, read once
    allowed = allowed_targets()
    failed: list[str] = []
    seen: set[tuple[str, str]] = set()
    found: dict[str, tuple[Any, bool]] = {}  # target -> (class, None or the import's exception; has the hook)
    for config in configs:
        for target, node in _stage_nodes(config if isinstance(config, dict) else plain_config(config)):
            if target not in allowed:
                continue
            if target not in found:
                try:
                    cls = locate(target)
                except Exception as exc:  # noqa: BLE001 - the job reports it
                    cls = exc
                found[target] = (cls, cls is None or isinstance(cls, Exception) or isinstance(cls, WarmsUp))
            cls, wanted = found[target]
            if not wanted:
                continue  # imported, and no hook: nothing to warm
            params = {str(k): v for k, v in node.items() if not str(k).startswith("_")}
            key = (target, json.dumps(params, sort_keys=True, default=repr))
            if key in seen:
                continue
            seen.add(key)
            if cls is None:
                failed.append(f"{target}: cannot be imported")
                continue
            if isinstance(cls, Exception):
                failed.append(f"{target}: {type(cls).__name__}: {cls}")
                continue
            try:
                cls.warm_up(params)
            except Exception as exc:  # noqa: BLE001 - the job reports it
                failed.append(f"{target}: {type(exc).__name__}: {exc}")
    return failed
