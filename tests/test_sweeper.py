"""Units of the nirspi sweeper that the CLI tests cannot force."""

from __future__ import annotations

from pathlib import Path

import pytest
from hydra.core.override_parser.overrides_parser import OverridesParser

from nirspi_pipe.app.jobcomposer import subdir_override


def test_hex_job_keys_stay_strings() -> None:
    # An unquoted 4703e54460190101 parses as the float inf: two jobs then shared a folder.
    for key in ("4703e54460190101", "0000000000000001", "1e10aaaaaaaaaaaa", "deadbeefdeadbeef"):
        (ov,) = OverridesParser.create().parse_overrides([subdir_override(key)])
        value = ov.value()
        assert isinstance(value, str) and value == key


# -- job keys come from Hydra's own composition -------------------------------------------------


def _experiments() -> list[str]:
    from importlib import resources

    folder = Path(str(resources.files("nirspi_pipe.experiments"))) / "experiment"
    return sorted(p.stem for p in folder.glob("*.yaml"))


@pytest.fixture(scope="module")
def hydra_loader():
    from hydra import initialize_config_module
    from hydra.core.global_hydra import GlobalHydra

    with initialize_config_module(config_module="nirspi_pipe.conf", version_base="1.3"):
        yield GlobalHydra.instance().config_loader()


def _sweeper_for(loader, experiment: str):  # type: ignore[no-untyped-def]
    from types import SimpleNamespace

    from hydra.types import RunMode
    from omegaconf import OmegaConf

    from nirspi_pipe.app.sweeper import NirspiSweeperBase

    cfg = loader.load_configuration("config", [f"+experiment={experiment}"], run_mode=RunMode.MULTIRUN)
    node = OmegaConf.to_container(cfg.hydra.sweeper, resolve=False)
    node.pop("_target_", None)
    sweeper = NirspiSweeperBase(**node)
    sweeper.hydra_context = SimpleNamespace(config_loader=loader)  # all the keying uses of it
    sweeper.config = cfg
    return sweeper


@pytest.mark.slow  # Hydra's full composition of 3 jobs of every shipped grid: 92 s of CPU
def test_every_shipped_experiment_is_keyed_as_hydra_composes_it(hydra_loader) -> None:
    """The fast keying path (one composition per structural override set) gives the keys of
    Hydra's own composition (``load_sweep_config``) for every shipped experiment: the first, a
    middle and the last job of each (keyed together, as the fast path groups them)."""
    names = _experiments()
    assert {"paper", "paper_ci", "table3", "figure9"} <= set(names)
    for name in names:
        if name == "pareto_search":  # Optuna's sweeper, not ours (tests/test_optuna.py runs it)
            continue
        sweeper = _sweeper_for(hydra_loader, name)
        grid = sweeper._expand([f"+experiment={name}"])
        assert grid, name
        picks = [grid[i] for i in sorted({0, len(grid) // 2, len(grid) - 1})]
        fast = sweeper.job_keys(picks)
        assert all(isinstance(k, str) for k in fast), (name, [k for k in fast if not isinstance(k, str)][:1])
        assert fast == sweeper.job_keys(picks, fast=False), name
