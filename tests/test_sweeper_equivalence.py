"""The sweeper composes every job as Hydra does (issue 27, item 3).

The sweeper does not compose each job through Hydra: it composes each distinct set of structural
overrides once, applies the plain ``key=value`` overrides itself and resolves the node references
itself (``NirspiSweeperBase._compose``; Hydra's composition costs ~0.1 s a job, the grids hold up to
3240 jobs; ``nirspi-bench compose`` measures both). These tests hold that its job configs are
Hydra's: for every shipped experiment, jobs that hypothesis draws from its full grid, with and
without extra command-line overrides, and its first and last job, compared with Hydra's public
``hydra.compose`` as resolved containers (``hydra`` node excluded, types included), with the
config-group choices and task overrides. ``nirspi-bench compose --check-all`` compares every job of
every grid (docs/architecture.md gives the count; the benchmarks run it).

The jobs drawn change every day: hypothesis is seeded with the date (``YYYYMMDD``, UTC), not
derandomised as the rest of the suite, so each CI run tests other jobs. The seed is in every
failure message; ``NIRSPI_EQUIVALENCE_SEED=<seed> pytest tests/test_sweeper_equivalence.py``
replays a run.
"""

from __future__ import annotations

import datetime as _dt
import os
import re
from typing import Any

import pytest
from hypothesis import HealthCheck, Phase, given, seed, settings
from hypothesis import strategies as st

from nirspi_pipe.benchmarks.compose import difference, experiments, fast_job, hydra_job, hydra_session, sweeper_for

EXPERIMENTS = experiments()

#: Today's seed (UTC date as YYYYMMDD), or the one to replay.
SEED = int(os.environ.get("NIRSPI_EQUIVALENCE_SEED") or _dt.datetime.now(_dt.timezone.utc).strftime("%Y%m%d"))
REPLAY = f"(hypothesis seed {SEED}: replay with NIRSPI_EQUIVALENCE_SEED={SEED})"

#: Few examples per test (Hydra composes each drawn job, ~0.1 s, and the sweeper each new set of
#: structural overrides), no shrinking (minutes at that cost; the failing example is printed as
#: drawn): the whole file stays well under a minute on 2 cores.
EQUIVALENCE = settings(
    max_examples=2,
    derandomize=False,  # seeded with the date instead (module docstring)
    database=None,
    deadline=None,
    phases=[Phase.explicit, Phase.reuse, Phase.generate],
    suppress_health_check=[HealthCheck.too_slow],
)


class Sweeps:
    """Hydra's loader, and each experiment's sweeper, grid and composition cache (as in a sweep)."""

    def __init__(self, loader: Any) -> None:
        self.loader = loader
        self._cache: dict[str, tuple[Any, list[list[str]], dict[Any, Any]]] = {}
        self._first: dict[str, Any] = {}

    def of(self, name: str) -> tuple[Any, list[list[str]], dict[Any, Any]]:
        if name not in self._cache:
            sweeper = sweeper_for(self.loader, name)
            self._cache[name] = (sweeper, sweeper._expand([f"+experiment={name}"]), {})
        return self._cache[name]

    def first_config(self, name: str) -> dict[str, Any]:
        """The resolved config of the experiment's first job, as Hydra composes it."""
        if name not in self._first:
            self.check(name, self.of(name)[1][0])
        return self._first[name]

    def check(self, name: str, job: list[str]) -> None:
        sweeper, grid, bases = self.of(name)
        hydra = hydra_job(job)
        found = difference(fast_job(sweeper, job, bases), hydra)
        assert found is None, f"+experiment={name}: job {' '.join(job)}: {found} {REPLAY}"
        if job == grid[0] and not isinstance(hydra, Exception):
            self._first[name] = hydra.config


@pytest.fixture(scope="module")
def sweeps():  # type: ignore[no-untyped-def]
    with hydra_session() as loader:
        yield Sweeps(loader)


def test_the_shipped_experiments_are_all_here() -> None:
    assert {"paper", "paper_ci", "table3", "figure9", "scan_order", "pareto", "departures"} <= set(EXPERIMENTS)


@pytest.mark.parametrize("name", EXPERIMENTS)
def test_first_and_last_job_compose_as_hydra_composes_them(sweeps: Sweeps, name: str) -> None:
    _, grid, _ = sweeps.of(name)
    assert grid, name
    for job in (grid[0], grid[-1]):
        sweeps.check(name, job)


@pytest.mark.slow  # two drawn jobs of each grid, composed by the sweeper and by Hydra: 31 s of CPU
@pytest.mark.parametrize("name", EXPERIMENTS)
@seed(SEED)
@EQUIVALENCE
@given(data=st.data())
def test_any_job_of_the_grid_composes_as_hydra_composes_it(sweeps: Sweeps, name: str, data: st.DataObject) -> None:
    _, grid, _ = sweeps.of(name)
    index = data.draw(st.integers(0, len(grid) - 1), label="job index")
    sweeps.check(name, grid[index])


# -- extra command-line overrides -----------------------------------------------------------------

_SIMPLE = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")


def _grid_values(grid: list[list[str]]) -> dict[str, list[str]]:
    """Each plain key of a grid and the values its jobs give it (``scene.distance_mm``: 150, 200)."""
    values: dict[str, list[str]] = {}
    for job in grid:
        for text in job:
            key, sep, value = text.partition("=")
            if sep and key[:1] not in "+~" and "@" not in key and not key.startswith("hydra"):
                if value not in values.setdefault(key, []):
                    values[key].append(value)
    return values


def _leaves(node: Any, path: str = "") -> dict[str, Any]:
    """The scalar leaves of a resolved config (``scene.distance_mm``: 200)."""
    out: dict[str, Any] = {}
    if isinstance(node, dict):
        for k, v in node.items():
            if isinstance(k, str) and _SIMPLE.match(k):
                out.update(_leaves(v, f"{path}{k}."))
    elif not isinstance(node, list):
        out[path.rstrip(".")] = node
    return out


def _value_like(current: Any) -> st.SearchStrategy[str]:
    """An override value (as typed on the command line) of the type of ``current``."""
    if isinstance(current, bool):
        return st.sampled_from(["true", "false"])
    if isinstance(current, int):
        return st.integers(0, 4096).map(str)
    if isinstance(current, float):
        return st.floats(1e-3, 1e3, allow_nan=False).map(repr)
    if current is None:
        return st.just("null")
    return st.from_regex(r"[a-z][a-z0-9_]{0,6}", fullmatch=True)


@st.composite
def _command_line(draw: st.DrawFn, grid: list[list[str]], config: dict[str, Any]) -> list[str]:
    """One or two extra command-line overrides: a grid key given again (one value, a sub-list, or
    forced with ``++``), a config leaf set (plain or ``++``), a key deleted, or a new key added."""
    values = _grid_values(grid)
    leaves = _leaves(config)
    out: list[str] = []
    for _ in range(draw(st.integers(1, 2))):
        kind = draw(st.sampled_from(["grid", "grid list", "grid ++", "leaf", "leaf ++", "delete", "add"]))
        if kind.startswith("grid") and values:
            key = draw(st.sampled_from(sorted(values)))
            picked = draw(st.lists(st.sampled_from(values[key]), min_size=1, max_size=2, unique=True))
            if kind == "grid list":
                out.append(f"{key}={','.join(picked)}")
            else:
                out.append(f"{'++' if kind == 'grid ++' else ''}{key}={picked[0]}")
        elif kind.startswith("leaf") or kind == "delete":
            key = draw(st.sampled_from(sorted(leaves)))
            if kind == "delete":
                out.append(f"~{key}")
            else:
                out.append(f"{'++' if kind == 'leaf ++' else ''}{key}={draw(_value_like(leaves[key]))}")
        else:
            out.append(f"+nirspi_extra={draw(st.integers(0, 9))}")
    return out


@pytest.mark.slow  # 12 drawn grids, each composed by the sweeper and by Hydra: 22 s of CPU
@seed(SEED)
@settings(EQUIVALENCE, max_examples=12)
@given(data=st.data())
def test_jobs_with_command_line_overrides_compose_as_hydra_composes_them(sweeps: Sweeps, data: st.DataObject) -> None:
    """``nirspi-run -m +experiment=NAME EXTRA...``: the grid as the sweeper expands it with the
    extra overrides (a key given again replaces its list), and a job of it, composed both ways."""
    name = data.draw(st.sampled_from(EXPERIMENTS), label="experiment")
    _, grid, _ = sweeps.of(name)
    extra = data.draw(_command_line(grid, sweeps.first_config(name)), label="command line")
    arguments = [f"+experiment={name}", *extra]
    try:
        sweeper = sweeper_for(sweeps.loader, name, extra)
        jobs = sweeper._expand(arguments)
    except Exception:  # noqa: BLE001 - nirspi-run stops before the sweep (a key it cannot add, ...)
        return
    job = jobs[data.draw(st.integers(0, len(jobs) - 1), label="job index")]
    found = difference(fast_job(sweeper, job, {}), hydra_job(job))
    assert found is None, f"nirspi-run -m {' '.join(arguments)}: job {' '.join(job)}: {found} {REPLAY}"


# -- regressions: cases the comparison found --------------------------------------------------------


def test_a_forced_override_after_a_grid_value_wins_as_in_hydra(sweeps: Sweeps) -> None:
    """``nirspi-run -m +experiment=departures ++illumination.klux=5``: Hydra applies ``key=value``
    and ``++key=value`` in their order, so the job's ``illumination.klux=15`` (from the grid) then
    ``++illumination.klux=5`` is 5; the sweeper applied the plain value after composing the
    ``++`` one and keyed and ran 15."""
    job = (
        "+experiment=table4_remesh scan=basic illumination.klux=15 scene=u_shape seed=0"
        " surface.remesh_iterations=3 ++illumination.klux=5 +nirspi_extra=0"
    ).split()
    sweeper, _, bases = sweeps.of("departures")
    composed = fast_job(sweeper, job, bases)
    assert not isinstance(composed, Exception), composed
    assert composed.config["illumination"]["klux"] == 5
    sweeps.check("departures", job)


def test_a_group_of_the_experiments_search_path_is_composed_once_per_option(sweeps: Sweeps) -> None:
    """scan_order sweeps ``mechanism`` (a group of ``experiments/``, on the search path that
    ``conf/config.yaml`` adds, which Hydra's loader does not list): each of its 480 jobs was
    composed in full by Hydra (53 s of keying) as a value it could not set."""
    sweeper, grid, _ = sweeps.of("scan_order")
    structural, updates, _ = sweeper._split(grid[-1])
    assert "mechanism=flicker" in structural and "+experiment=scan_order" in structural
    assert {str(u.key_or_group) for u in updates} == {"scan.ratio", "seed"}
