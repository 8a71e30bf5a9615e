"""How close Optuna's search (``pareto_search``) came to the exhaustive fronts, and at what cost.

    python experiments/reconstructor/compare_fronts.py GRID SEARCH [--small SMALL] [--replay SAMPLER …]

GRID: a ``pareto_grid`` sweep folder (all 144 configurations); SEARCH: a ``pareto_search`` folder
(hydra/sweeper=optuna, its job folders numbered in trial order); SMALL (optional): a
``pareto_small`` folder, whose 64² ``image`` jobs are the part of the grid without fixed weights.
Prints Markdown: each sweep's jobs and summed job time, the grid's front (PSNR up, solver time
down), which of its configurations the search tried and at which trial, and the hypervolume of
the search's front as a share of the grid's after each number of trials.

Solver times differ between two runs of one configuration (the machine is shared), so the search
is scored with the grid's recorded values of the configurations it tried: "found" means it ran
the same configuration, and the hypervolume is the grid's, restricted to those configurations.
The hypervolume is measured in (log10 solver time, PSNR), from the grid's slowest time and lowest
PSNR (every configuration counts, none dominates the reference point). ``--replay`` runs Optuna's
samplers against the grid's records (no jobs) for seeds 0-7: how pareto_search's sampler was chosen.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import pandas as pd

from nirspi_pipe.app.objective import pareto_mask
from nirspi_pipe.app.results import collect

KEYS = ("reconstructor", "scan", "scan.ratio")
OBJ = ("metrics.psnr", "timings_ms.solver")
DIRS = ("maximize", "minimize")


def _config(row: pd.Series) -> tuple:
    return tuple(row[k] for k in KEYS)


def hypervolume(psnr: np.ndarray, time_ms: np.ndarray, ref_psnr: float, ref_log_t: float) -> float:
    """Area dominated by the points in (log10 time ↓, PSNR ↑) up to the reference point."""
    if len(psnr) == 0:
        return 0.0
    mask = pareto_mask(np.column_stack([psnr, time_ms]), DIRS)
    x, y = np.log10(time_ms[mask]), psnr[mask]
    order = np.argsort(x)
    x, y = x[order], y[order]
    edges = np.append(x[1:], ref_log_t)
    return float(np.sum((edges - x) * (y - ref_psnr)))


SAMPLERS = {
    "tpe": lambda seed: _samplers().TPESampler(seed=seed),
    "tpe_multivariate": lambda seed: _samplers().TPESampler(seed=seed, multivariate=True),
    "motpe": lambda seed: _samplers().MOTPESampler(seed=seed),
    "nsgaii": lambda seed: _samplers().NSGAIISampler(seed=seed),
    "random": lambda seed: _samplers().RandomSampler(seed=seed),
}


def _samplers():  # type: ignore[no-untyped-def]
    import optuna

    return optuna.samplers


def replay(grid: pd.DataFrame, sampler: str, seeds: range, trials: int = 100, batch: int = 4) -> np.ndarray:
    """Optuna's ``sampler`` run against the grid's recorded values instead of jobs, as
    hydra-optuna-sweeper asks (``batch`` trials at a time, the dimensions in pareto_grid's order):
    per seed, the hypervolume share of the tried configurations' front, their number, and the grid
    front's configurations among them."""
    import warnings

    import optuna
    from optuna.distributions import CategoricalDistribution

    optuna.logging.set_verbosity(optuna.logging.ERROR)
    values = {_config(r): (r[OBJ[0]], r[OBJ[1]]) for _, r in grid.iterrows()}
    front = {_config(r) for _, r in grid[pareto_mask(grid[list(OBJ)].to_numpy(dtype=float), DIRS)].iterrows()}
    space = {k: CategoricalDistribution(list(dict.fromkeys(grid[k]))) for k in KEYS}
    ref_psnr, ref_log_t = float(grid[OBJ[0]].min()), float(np.log10(grid[OBJ[1]].max()))
    hv_grid = hypervolume(grid[OBJ[0]].to_numpy(dtype=float), grid[OBJ[1]].to_numpy(dtype=float), ref_psnr, ref_log_t)
    out = []
    for seed in seeds:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # Optuna's ExperimentalWarning (multivariate TPE)
            study = optuna.create_study(directions=list(DIRS), sampler=SAMPLERS[sampler](seed))
            tried: list[tuple] = []
            while len(tried) < trials:
                asked = [study.ask() for _ in range(min(batch, trials - len(tried)))]
                for trial in asked:
                    config = tuple(trial._suggest(k, d) for k, d in space.items())  # as the sweeper does
                    tried.append(config)
                    study.tell(trial, values=list(values[config]))
        seen = np.array([values[c] for c in dict.fromkeys(tried)], dtype=float)
        hv = hypervolume(seen[:, 0], seen[:, 1], ref_psnr, ref_log_t) / hv_grid
        out.append((hv, len(seen), sum(c in front for c in dict.fromkeys(tried))))
    return np.array(out)


def _jobs_s(frame: pd.DataFrame) -> float:
    return float(frame["timings_ms.total"].sum() / 1000.0)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("grid", type=Path)
    parser.add_argument("search", type=Path)
    parser.add_argument("--small", type=Path, default=None)
    parser.add_argument(
        "--replay", nargs="*", default=None, metavar="SAMPLER", help=f"also replay: {', '.join(SAMPLERS)}"
    )
    ns = parser.parse_args(argv)

    grid = collect(ns.grid, write=False)
    grid = grid[grid["status"] == "ok"].reset_index(drop=True)
    values = {_config(r): (r[OBJ[0]], r[OBJ[1]]) for _, r in grid.iterrows()}
    front = pareto_mask(grid[list(OBJ)].to_numpy(dtype=float), DIRS)
    front_configs = [_config(r) for _, r in grid[front].sort_values(OBJ[1]).iterrows()]

    search = collect(ns.search, write=False)
    search = search.assign(trial=pd.to_numeric(search["job"])).sort_values("trial").reset_index(drop=True)
    tried = [_config(r) for _, r in search.iterrows()]
    first = {}
    for i, c in enumerate(tried):
        first.setdefault(c, i + 1)

    ref_psnr = float(grid[OBJ[0]].min())
    ref_log_t = float(np.log10(grid[OBJ[1]].max()))
    psnr_all, t_all = grid[OBJ[0]].to_numpy(dtype=float), grid[OBJ[1]].to_numpy(dtype=float)
    hv_grid = hypervolume(psnr_all, t_all, ref_psnr, ref_log_t)

    def hv_after(n: int) -> float:
        seen = [values[c] for c in dict.fromkeys(tried[:n]) if c in values]
        arr = np.array(seen, dtype=float).reshape(-1, 2)
        return hypervolume(arr[:, 0], arr[:, 1], ref_psnr, ref_log_t) / hv_grid

    print(f"grid: {len(grid)} ok jobs, {_jobs_s(grid):.1f} s of job time; front {len(front_configs)} configurations")
    print(
        f"search: {len(search)} trials ({int((search['status'] == 'ok').sum())} ok), "
        f"{len(set(tried))} distinct configurations, {_jobs_s(search):.1f} s of job time"
    )
    print()
    print("| grid front: reconstructor | scan | ratio | PSNR (dB) | solver (ms) | search found it at trial |")
    print("|---|---|---:|---:|---:|---:|")
    for c in front_configs:
        p, t = values[c]
        print(f"| {c[0]} | {c[1]} | {c[2]:g} | {p:.2f} | {t:.3g} | {first.get(c, '—')} |")
    found = sum(c in first for c in front_configs)
    print()
    print(f"found {found} of {len(front_configs)} front configurations in {len(search)} trials")
    marks = [n for n in (10, 20, 30, 40, 50, 60, 70, 80, 90, 100) if n <= len(tried)]
    print(
        "hypervolume of the search's front / the grid's, after n trials (grid values): "
        + ", ".join(f"{n}: {hv_after(n):.3f}" for n in marks)
    )
    for name in ns.replay if ns.replay is not None else []:
        r = replay(grid, name, range(8))
        print(
            f"replay {name}, seeds 0-7: hypervolume share {r[:, 0].mean():.3f} ± {r[:, 0].std():.3f} "
            f"(min {r[:, 0].min():.3f}), {r[:, 1].mean():.0f} distinct configurations, "
            f"{r[:, 2].mean():.1f} of {len(front_configs)} front configurations"
        )
    if ns.small is not None:
        small = collect(ns.small, write=False)
        small_ok = small[small["status"] == "ok"]
        part = small_ok[(small_ok["camera.resolution"] == 64) & (small_ok["scene"] == "image")]
        part = part.assign(reconstructor=part["solver"])
        sm_front = pareto_mask(part[list(OBJ)].to_numpy(dtype=float), DIRS)
        sm_configs = [_config(r) for _, r in part[sm_front].sort_values(OBJ[1]).iterrows()]
        sm_found = [c for c in sm_configs if c in first]
        print()
        print(
            f"pareto_small: {len(small)} jobs ({len(small_ok)} ok), {_jobs_s(small_ok):.1f} s of job time; "
            f"its 64² image part: {len(part)} jobs, front {len(sm_configs)} configurations: "
            + ", ".join(f"{c[0]}/{c[1]}/{c[2]:g}" for c in sm_configs)
        )
        print(
            f"the search tried {len(sm_found)} of them"
            + (" (at trials " + ", ".join(str(first[c]) for c in sm_found) + ")" if sm_found else "")
        )


if __name__ == "__main__":
    main()
