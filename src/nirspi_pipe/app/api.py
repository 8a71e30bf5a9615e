"""The Python API: run one configuration, read a sweep's results.

    >>> import nirspi_pipe
    >>> result = nirspi_pipe.run(["fog=chamber", "scan=spiral"])      # doctest: +SKIP
    >>> result.metrics["psnr"], result.reconstruction.shape          # doctest: +SKIP

:func:`run` composes the configuration exactly as ``nirspi-run`` does (the same config files,
experiments and installed plugins, through Hydra's public compose API), runs the pipeline in
this process and returns a :class:`RunResult`. It writes nothing unless ``output_dir`` is given,
in which case the folder gets what a ``nirspi-run`` job writes (``record.json``, ``arrays.npz``,
``summary.png``, …). :func:`load_results` returns a sweep's table as a pandas DataFrame.
docs/api.md has a worked, doctested example.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from types import MappingProxyType
from typing import TYPE_CHECKING, Any

from nirspi_pipe.app.registration import register_hydra_plugins
from nirspi_pipe.errors import NirspiError
from nirspi_pipe.summary import format_summary

if TYPE_CHECKING:  # keep `import nirspi_pipe` cheap: numpy/pandas/hydra load on first use
    import numpy as np
    import pandas as pd

    from nirspi_pipe.stages import Products

__all__ = ["BadOverrides", "BadResults", "RunFailed", "RunResult", "compose", "load_results", "run"]


class BadOverrides(NirspiError, ValueError):
    """Overrides that do not compose (unknown option, bad syntax, a command-line flag)."""


class BadResults(NirspiError, ValueError):
    """A results file that cannot be read as a table (the message names it)."""


class RunFailed(NirspiError):
    """A run with an output folder failed; the message is the error, ``error.txt`` the traceback."""


@dataclass(frozen=True)
class RunResult:
    """What one run produced (read-only).

    Attributes:
        config: the resolved configuration (lengths in the units its keys name).
        choices: the option of every config group (``{"fog": "chamber", "sfs": None, …}``).
        overrides: the overrides it was composed with.
        seed: the seed the run used (``cfg.seed``, or derived from the config hash when null).
        metrics: scores against the ground truth (``ssim``, ``psnr`` in dB, ``rmse``, and the 3D
            ones of ``metrics=full``); see :data:`nirspi_pipe.summary.METRIC_HELP`.
        timings_ms: milliseconds per stage, and ``total``.
        derived: physical quantities the source used (``beta_per_m``, ``visibility_m``,
            ``snr_db``, ``klux``, …).
        info: per-stage bookkeeping (iterations, stop reasons, …).
        warnings: warnings raised during the run.
        products: every stage's typed output (:class:`nirspi_pipe.stages.Products`).
        output_dir: the folder written, or None.
    """

    config: Mapping[str, Any]
    choices: Mapping[str, str | None]
    overrides: tuple[str, ...]
    seed: int
    metrics: Mapping[str, float]
    timings_ms: Mapping[str, float]
    derived: Mapping[str, float]
    info: Mapping[str, Mapping[str, Any]]
    warnings: tuple[str, ...]
    products: Products
    output_dir: Path | None = None

    @property
    def reconstruction(self) -> np.ndarray:
        """The reconstructed image, relative radiance (white target = 1), ``(n, n)``."""
        return self.products.image.data

    @property
    def truth(self) -> np.ndarray | None:
        """The true radiance on the same grid (None for measured data)."""
        return None if self.products.truth is None else self.products.truth.radiance

    @property
    def error(self) -> np.ndarray | None:
        """``reconstruction − truth`` (None without a ground truth)."""
        t = self.truth
        return None if t is None else self.reconstruction - t

    def record(self) -> dict[str, Any]:
        """The run as a record dict, in the layout of ``record.json`` (without provenance)."""
        return {
            "config": dict(self.config),
            "choices": dict(self.choices),
            "metrics": dict(self.metrics),
            "timings_ms": dict(self.timings_ms),
            "derived": dict(self.derived),
            "info": {k: dict(v) for k, v in self.info.items()},
            "meta": {
                "seed": self.seed,
                "status": "ok",
                "warnings": list(self.warnings),
                "overrides": list(self.overrides),
            },
        }

    def summary(self) -> str:
        """The text ``nirspi-run`` prints: active effects, explained metrics, stage times."""
        return format_summary(self.record(), self.output_dir)

    def save_figure(self, folder: str | Path) -> Path:
        """Write the run's ``summary.png`` into ``folder``; returns its path."""
        from nirspi_pipe.figure import write_summary_figure  # start-up: loads numpy (117 ms here)

        folder = Path(folder)
        return write_summary_figure(folder, self.products, self.record(), mesh_png=folder / "mesh.png")


def _frozen(mapping: Mapping[str, Any]) -> Mapping[str, Any]:
    return MappingProxyType(dict(mapping))


def _override_list(overrides: Any) -> list[str]:
    """``overrides`` as a list of strings, or :class:`BadOverrides` naming the argument: a single
    string (``"a=1"``, whose characters would be taken one by one), a mapping or anything but
    strings in a list is refused, with the list it should have been when that is clear."""
    from nirspi_pipe.safeio import short_repr  # start-up: loads numpy (111 ms here)

    allowed = "a list of 'key=value' strings"
    if isinstance(overrides, (str, bytes)):
        text = overrides.decode(errors="replace") if isinstance(overrides, bytes) else overrides
        raise BadOverrides(
            f"overrides={short_repr(overrides, 80)} is a single string; allowed: {allowed}, "
            f"e.g. {short_repr(text.split(), 80)}"
        )
    if isinstance(overrides, Mapping):
        example = [f"{k}={v}" for k, v in list(overrides.items())[:4]]
        raise BadOverrides(
            f"overrides={short_repr(overrides, 80)} is a mapping; allowed: {allowed}, e.g. {short_repr(example, 80)}"
        )
    if not hasattr(overrides, "__iter__"):
        raise BadOverrides(f"overrides={short_repr(overrides, 80)} is not a list; allowed: {allowed}")
    items = list(overrides)
    for i, item in enumerate(items):
        if not isinstance(item, str):
            raise BadOverrides(
                f"overrides[{i}]={short_repr(item, 80)} is not a string; allowed: {allowed}, e.g. 'seed=1'"
            )
    return items


def compose(overrides: Sequence[str] = ()) -> tuple[Any, dict[str, str | None]]:
    """The composed config of ``overrides`` (an OmegaConf ``DictConfig`` without the ``hydra``
    node, as a ``nirspi-run`` job sees it) and the group choices. Raises :class:`BadOverrides`
    (a :class:`ValueError`) with one line for an unknown option or a bad override."""
    from hydra.core.global_hydra import GlobalHydra  # start-up: loads hydra, omegaconf (148 ms here)
    from omegaconf import open_dict  # start-up: loads omegaconf, yaml (62 ms here)

    from nirspi_pipe.app.entry import check_invocation  # start-up: loads hydra, hydra_plugins (290 ms here)
    from nirspi_pipe.app.flags import Refused  # start-up: with the entry check above
    from nirspi_pipe.app.plugins import activate  # start-up: loads hydra, omegaconf (142 ms here)

    overrides = _override_list(overrides)
    if GlobalHydra.instance().is_initialized():
        raise NirspiError("nirspi_pipe.run cannot be called inside a running Hydra app; call run_pipeline(cfg)")
    activate()  # installed plugins' config folders join the search path (never the working directory's)
    register_hydra_plugins()
    try:  # the same check as nirspi-run's: the composed config, Hydra's node included
        cfg = check_invocation(overrides, api=True).config
    except Refused as exc:
        raise BadOverrides(str(exc)) from None
    choices = {k: v for k, v in cfg.hydra.runtime.choices.items() if not k.startswith("hydra/")}
    with open_dict(cfg):
        del cfg["hydra"]
    return cfg, choices


def run(overrides: Sequence[str] = (), *, output_dir: str | Path | None = None) -> RunResult:
    """Run one configuration given as ``nirspi-run`` overrides and return its :class:`RunResult`.

    Args:
        overrides: e.g. ``["fog=chamber", "scan=spiral", "scan.ratio=0.25"]``; the same syntax
            and defaults as the command line (``+experiment=NAME`` works; sweeps do not).
        output_dir: write the job's files (``record.json``, ``arrays.npz``, PNGs, ``summary.png``)
            into this folder; None (default) writes nothing.

    Raises:
        BadOverrides / ConfigError (both ValueError): bad configuration, with a one-line message
            naming the key and the allowed values.
        RunFailed: with ``output_dir``, the run failed (its traceback is in ``error.txt``).
    """
    overrides = _override_list(overrides)  # once: a generator is read once
    cfg, choices = compose(overrides)
    # start-up: loads 63 modules of ours (27 ms here)
    from nirspi_pipe.instantiate import Plan

    plan = Plan.of(cfg)  # the one conversion to plain data; the runner builds from it (issue 42)
    if output_dir is not None:
        from nirspi_pipe.app.jobs import execute_job  # start-up: loads hydra, hydra_plugins (335 ms here)

        kept: list[Any] = []
        folder = Path(output_dir)
        record = execute_job(plan, folder, dict(choices), list(overrides), on_output=kept.append)  # type: ignore[arg-type]
        if record["meta"]["status"] != "ok" or not kept:
            raise RunFailed(f"{record['meta']['error']} (traceback: {folder / 'error.txt'})")
        out = kept[0]
    else:
        from nirspi_pipe.app.configs import scan_indices  # start-up: loads hydra, hydra_plugins (304 ms here)
        from nirspi_pipe.pipeline import run_pipeline  # start-up: loads numpy (158 ms here)

        out = run_pipeline(plan, scan_indices=scan_indices)
        folder = None
    return RunResult(
        config=_frozen(plan.config),
        choices=_frozen(choices),
        overrides=tuple(overrides),
        seed=int(out.info["run"]["seed"]),
        metrics=_frozen(out.metrics),
        timings_ms=_frozen(out.timings_ms),
        derived=_frozen(out.derived),
        info=_frozen({k: _frozen(v) for k, v in out.info.items()}),
        warnings=tuple(out.warnings),
        products=out.products,
        output_dir=folder,
    )


def load_results(path: str | Path, *, refresh: bool = False) -> pd.DataFrame:
    """A sweep's results as a DataFrame: one row per job, columns as in README's Run section
    (``scan``, ``illumination.klux``, ``metrics.psnr``, ``timings_ms.solver``, ``status``, …).

    ``path`` is a sweep folder (``hydra.sweep.dir``) or a ``results.parquet``/``.csv`` file. A
    folder's ``results.parquet`` is read when present; without it, or with ``refresh``, the
    table is rebuilt from the jobs' ``record.json`` files (nothing is written).
    """
    from nirspi_pipe.app.results import collect  # start-up: loads hydra, cloudpickle, dateutil (748 ms here)

    p = Path(path)
    if p.is_file():
        if p.suffix not in (".parquet", ".csv"):
            raise ValueError(f"{p}: not a results file; allowed: a sweep folder, results.parquet or results.csv")
        return _read_table(p)
    if not p.is_dir():
        raise FileNotFoundError(f"{p}: no such sweep folder or results file")
    if (p / "results.parquet").is_file() and not refresh:
        return _read_table(p / "results.parquet")
    return collect(p, write=False)


def _read_table(p: Path) -> pd.DataFrame:
    """A ``.parquet`` or ``.csv`` table; :class:`BadResults` naming the file when it is not one
    (an empty CSV, as a sweep without records writes it, is an empty table)."""
    import pandas as pd  # start-up: loads pandas, pyarrow, cloudpickle (446 ms here)

    try:
        return pd.read_parquet(p) if p.suffix == ".parquet" else pd.read_csv(p)
    except pd.errors.EmptyDataError:
        return pd.DataFrame()
    except (ValueError, OSError, UnicodeDecodeError, pd.errors.ParserError) as exc:  # ArrowInvalid is a ValueError
        text = " ".join(str(exc).split())[:200] or type(exc).__name__
        kind = "Parquet" if p.suffix == ".parquet" else "CSV"
        raise BadResults(
            f"{p}: not a readable results table ({kind}: {text}); allowed: the results.parquet or results.csv "
            "that nirspi-run or nirspi-collect wrote"
        ) from None
