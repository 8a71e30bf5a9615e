"""The one checked entry path to Hydra (issue 32): ``nirspi-run`` (every flag and ``-m``) and the
Python API reach Hydra only through :func:`check_invocation`, which fails closed.

1. **Flags are matched exactly** against :data:`~nirspi_pipe.app.flags.FLAGS` before anything
   else (:mod:`nirspi_pipe.app.flags`). Hydra then gets the canonical spelling.
2. ``-cd DIR`` becomes a ``hydra.searchpath`` override, so the check and Hydra use the same
   search path *by construction*: Hydra never sees ``-cd``.
3. **The composed configuration is checked**, Hydra's node included, with Hydra's public compose
   API, the same config name and the same overrides Hydra gets
   (:mod:`nirspi_pipe.app.composition`). A configuration that does not compose is refused (one
   line), never handed on.
4. **Hydra's node is compared** with the one composed without the user's overrides, config
   folder or config name (only the ``hydra/…`` choices kept); a difference outside the allow-list
   of :mod:`nirspi_pipe.app.allowlist` is refused (:mod:`nirspi_pipe.app.hydranode`, which also
   holds the job gate :func:`~nirspi_pipe.app.hydranode.check_job`). The job part is checked as
   before (:mod:`nirspi_pipe.app.validate`: allowed targets, known keys, types).
5. **Sweeps** (this module): each swept value (command line and ``hydra.sweeper.params``) is
   checked for its key; a sweep that cannot be enumerated (Optuna's ``interval(a,b)``) by its
   bounds. A swept config group whose options may come from a user's folder (``-cd``, a
   ``hydra.searchpath`` entry) is composed once per value and checked in full.

Refusals raise :class:`~nirspi_pipe.app.flags.Refused` (one line; ``nirspi-run`` prints it with
exit 2, the API raises :class:`~nirspi_pipe.app.api.BadOverrides`).
"""

from __future__ import annotations

import itertools
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from hydra.core.override_parser.types import Glob, IntervalSweep
from omegaconf import OmegaConf
from omegaconf.errors import InterpolationKeyError, InterpolationResolutionError

from nirspi_pipe.app.composition import (
    compose_config,
    default_searchpath,
    one_line,
    parse_overrides,
    primary_exists,
    short_value,
)
from nirspi_pipe.app.configs import CONFIG_NAME, all_groups, group_options
from nirspi_pipe.app.flags import Refused, hydra_flags, parse_args
from nirspi_pipe.app.hydranode import (
    APPROVED,
    check_hydra_node,
    check_node_paths,
    check_override_places,
    check_searchpath,
    comparable_leaves,
    kind_of,
)
from nirspi_pipe.app.hydratargets import check_target, check_targets
from nirspi_pipe.errors import ConfigError
from nirspi_pipe.instantiate import Plan

__all__ = ["GATED_BEFORE_LAUNCH", "MAX_CHECKED_COMBINATIONS", "Invocation", "check_invocation"]

_SHELLS = ("bash", "zsh", "fish")


@dataclass(frozen=True)
class Invocation:
    """A checked invocation.

    Attributes:
        flags: canonical flag → value (None for a switch).
        overrides: the overrides as checked and as Hydra gets them (``-cd`` turned into
            ``hydra.searchpath``, ``group=null`` into the group's ``off`` option).
        hydra_argv: what Hydra's argument parser gets: canonical flags, then the overrides.
        config_name: the primary config's name.
        config: the composed configuration that was checked (Hydra's node included).
    """

    flags: dict[str, str | None] = field(default_factory=dict)
    overrides: tuple[str, ...] = ()
    hydra_argv: tuple[str, ...] = ()
    config_name: str = CONFIG_NAME
    config: Any = field(default=None, compare=False, repr=False)

    @property
    def multirun(self) -> bool:
        return "--multirun" in self.flags


# --------------------------------------------------------------------------- sweeps


def _candidates(ov: Any, group_opts: list[str] | None) -> list[Any]:
    """The values a sweep override can take: every one of a choice or range; the bounds of an
    interval (Optuna's ``interval(a,b)``); the matching options of a ``glob`` over a group."""
    value = ov.value()
    if isinstance(value, IntervalSweep):
        return [value.start, value.end]
    if isinstance(value, Glob):
        if group_opts is None:
            raise Refused(f"{ov.key_or_group}: glob() is allowed only over a config group")
        return list(value.filter(group_opts))
    try:
        return list(ov.sweep_iterator())
    except Exception as exc:  # noqa: BLE001 - what cannot be enumerated is refused
        raise Refused(f"{ov.key_or_group}={ov.input_line}: the sweep cannot be enumerated ({one_line(exc)})") from None


def _is_hydra_key(key: str) -> bool:
    return key == "hydra" or key.startswith(("hydra.", "hydra/"))


# --------------------------------------------------------------------------- the check


def check_invocation(args: list[str], *, api: bool = False) -> Invocation:
    """Check what ``nirspi-run ARGS`` (or ``nirspi_pipe.run(ARGS)`` with ``api``) would do and
    return the :class:`Invocation` to hand to Hydra; :class:`Refused` (one line) otherwise.

    The steps, in order: the API takes overrides only; flags are matched exactly
    (:func:`parse_args`); ``-sc`` takes one shell word, other overrides have their nulls rewritten;
    ``-cd`` becomes a search-path entry; sweeps only with ``-m`` and never of Hydra's settings; the
    primary config must exist; then one composition, checked whole (:func:`_compose_checked`), and
    each sweep's values (:func:`_check_sweeps`)."""
    if api:
        _refuse_flags_in_api(args)
    flags, overrides = parse_args(list(args))
    overrides, compose_overrides = _job_overrides(flags, overrides)
    _check_searchpath_first(parse_overrides(compose_overrides))  # before anything is composed or imported
    user_paths = bool(flags.get("--config-dir")) or any(
        ov.key_or_group == "hydra.searchpath" for ov in parse_overrides(compose_overrides)
    )
    overrides, compose_overrides = _with_config_dir(flags, overrides, compose_overrides)
    parsed = parse_overrides(compose_overrides)
    check_override_places(parsed)
    _check_sweep_places(parsed, flags)
    config_name = _primary_config(flags)
    fixed = [o for o, ov in zip(compose_overrides, parsed, strict=True) if not ov.is_sweep_override()]
    name_options = not user_paths and "--shell-completion" not in flags  # one-line names for options and keys
    cfg = _compose_checked(config_name, fixed, compose_overrides, name_options)
    simple = None
    if config_name == CONFIG_NAME and not user_paths:
        simple = _hydra_keys_if_plain([ov for ov in parsed if not ov.is_sweep_override()])
    _check_composed(cfg, flags, simple)
    sweeps = [ov for ov in parsed if ov.is_sweep_override()]
    _check_sweeps(cfg, sweeps, fixed, config_name, user_paths, flags)
    APPROVED.append(comparable_leaves(OmegaConf.to_container(cfg.hydra, resolve=False)))  # type: ignore[arg-type]
    del APPROVED[:-16]  # the latest few: a notebook calling nirspi_pipe.run in a loop keeps no more
    return Invocation(
        flags=flags,
        overrides=tuple(overrides),
        hydra_argv=(*hydra_flags(flags), *overrides),
        config_name=config_name,
        config=cfg,
    )


def _refuse_flags_in_api(args: list[str]) -> None:
    """``nirspi_pipe.run(ARGS)`` takes overrides only: no flag."""
    for arg in args:
        if arg.startswith("-"):
            raise Refused(f"{arg[:60]} is not an override; allowed: key=value overrides (sweeps: nirspi-run -m)")


def _job_overrides(flags: dict[str, str | None], overrides: list[str]) -> tuple[list[str], list[str]]:
    """``(overrides for Hydra, overrides to compose)``: with ``-sc`` the one shell word is
    checked and nothing of it is composed; otherwise ``stage=null``/``off`` are rewritten
    (:func:`nirspi_pipe.app.validate.rewrite_nulls`) and both lists are the rewritten ones."""
    from nirspi_pipe.app import validate  # start-up: loads 15 modules of ours (27 ms here)

    if "--shell-completion" in flags:
        words = [o.partition("=") for o in overrides]
        if len(words) != 1 or words[0][0] not in ("install", "uninstall", "query") or words[0][2] not in _SHELLS:
            raise Refused(
                "-sc needs exactly one of install=SHELL, uninstall=SHELL, query=SHELL; allowed shells: "
                + ", ".join(_SHELLS)
            )
        if words[0][0] == "query" and "COMP_LINE" not in os.environ:  # Hydra would raise KeyError
            raise Refused(
                "-sc query=SHELL is what an installed completion calls, with COMP_LINE set by the shell; "
                "allowed here: -sc install=SHELL (then press TAB) or -sc uninstall=SHELL"
            )
        return overrides, []
    rewritten, problem = validate.rewrite_nulls(overrides)
    if problem:
        raise Refused(problem)
    return rewritten, rewritten


def _with_config_dir(
    flags: dict[str, str | None], overrides: list[str], compose_overrides: list[str]
) -> tuple[list[str], list[str]]:
    """``-cd DIR`` (taken out of ``flags``) as what Hydra does with it: DIR appended to the
    search path, one ``hydra.searchpath=[...]`` override in place of any given. Returns
    ``(overrides for Hydra, overrides to compose)``."""
    config_dir = flags.pop("--config-dir", None)
    if config_dir is None:
        return overrides, compose_overrides
    folder = Path(config_dir).resolve()
    if not folder.is_dir():
        raise Refused(f"--config-dir={config_dir!r} is not allowed; allowed: a folder that exists")
    parsed = parse_overrides(compose_overrides)
    given = [ov for ov in parsed if ov.key_or_group == "hydra.searchpath"]
    base = given[-1].value() if given else default_searchpath()
    if not isinstance(base, list):
        raise Refused("hydra.searchpath is not allowed; allowed: a list of folders")
    entries = [*map(str, base), folder.as_uri()]
    compose_overrides = [o for o, ov in zip(compose_overrides, parsed, strict=True) if ov not in given]
    compose_overrides.append(f"hydra.searchpath=[{','.join(entries)}]")
    if "--shell-completion" not in flags:
        overrides = compose_overrides
    return overrides, compose_overrides


def _check_searchpath_first(parsed: list[Any]) -> None:
    """``hydra.searchpath`` overrides checked before the first composition (issue 41): Hydra
    imports a ``pkg://`` or ``structured://`` entry's module while it composes, so an entry that
    is not a default one or an existing ``file://`` folder is refused before that."""
    for ov in parsed:  # a package under hydra (+x@hydra.searchpath) is refused before compose too
        if ov.key_or_group != "hydra.searchpath":
            continue
        if ov.is_sweep_override() or ov.is_delete():
            raise Refused(f"{ov.input_line[:80]} is not allowed; allowed: hydra.searchpath=[file:///a/folder, ...]")
        problem = check_searchpath(ov.value())
        if problem:
            raise Refused(f"hydra.searchpath={short_value(ov.value())} is not allowed; allowed: {problem}")


def _check_sweep_places(parsed: list[Any], flags: dict[str, str | None]) -> None:
    """A sweep only with ``-m``, and never of Hydra's own settings."""
    for ov in parsed:
        if ov.is_sweep_override() and _is_hydra_key(ov.key_or_group):
            raise Refused(f"{ov.input_line}: sweeping Hydra's own settings is not allowed")
        if ov.is_sweep_override() and "--multirun" not in flags:
            raise Refused(f"{ov.input_line} is a sweep; allowed: a sweep with -m only (nirspi-run -m ...)")


def _primary_config(flags: dict[str, str | None]) -> str:
    """The primary config's name (``-cn``): ours, or another config of nirspi-pipe's conf/."""
    config_name = flags.get("--config-name") or CONFIG_NAME
    if config_name != CONFIG_NAME and not primary_exists(config_name):
        raise Refused(
            f"--config-name={config_name}: no such primary config; allowed: {CONFIG_NAME} or a config of "
            "nirspi-pipe's conf/ (files in a -cd folder are used as +experiment=NAME or group options)"
        )
    return config_name


def _compose_checked(config_name: str, fixed: list[str], compose_overrides: list[str], name_options: bool) -> Any:
    """The one composition (the sweeps' first values aside), with the job's keys and types
    checked on it; with ``name_options`` a refusal names the option or key rather than quoting
    Hydra's first line."""
    from nirspi_pipe.app import validate  # start-up: loads 15 modules of ours (27 ms here)

    try:
        cfg = compose_config(config_name, fixed)
    except Refused:
        problem = validate.check_overrides(compose_overrides) if name_options else None
        if problem:  # the option or key by name, rather than Hydra's first line
            raise Refused(problem) from None
        raise
    if name_options:
        problem = validate.check_overrides(compose_overrides, composed=cfg)  # keys and types on this compose
        if problem:
            raise Refused(problem)
    return cfg


def _plain(cfg: Any) -> tuple[dict[str, Any], dict[str, Any]]:
    """The job part (resolved where it resolves) and Hydra's node (unresolved)."""
    job_part = OmegaConf.masked_copy(cfg, [str(k) for k in cfg if k != "hydra"])
    try:
        job = OmegaConf.to_container(job_part, resolve=True)
    except (InterpolationKeyError, InterpolationResolutionError) as exc:
        names_hydra = "'hydra." in str(exc)  # ${hydra.job.name}: Hydra's node is masked out here
        if (isinstance(exc, InterpolationKeyError) and not names_hydra) or "Recursive interpolation" in str(exc):
            key = getattr(exc, "full_key", None) or "?"
            raise Refused(
                f"{key}: the interpolation does not resolve ({one_line(str(exc).splitlines()[0])}); "
                "allowed: a value, or ${other.key} naming another key"
            ) from None
        job = OmegaConf.to_container(job_part, resolve=False)  # a resolver only a running app has
    except Exception:  # noqa: BLE001 - then checked unresolved
        job = OmegaConf.to_container(job_part, resolve=False)
    hydra_node = OmegaConf.to_container(cfg.hydra, resolve=False)
    return job, hydra_node  # type: ignore[return-value]


def _hydra_keys_if_plain(fixed: list[Any]) -> list[str] | None:
    """The ``hydra.…`` keys (below ``hydra.``) that ``fixed`` sets, when Hydra's node can differ
    from the default composition only at those keys or through trusted files; otherwise None.

    That holds when (the caller checks) the config is the default one and the search path is
    the default one (no ``-cd``, no ``hydra.searchpath``), and every override in ``fixed`` is
    either a choice of a job's config group (``scene=cube``, ``+experiment=paper_ci``: an option
    file of nirspi-pipe or an installed plugin, which is trusted and may set Hydra's settings) or
    a plain value override of an existing key (no ``+``/``~``/``@``), each ``hydra.…`` one
    setting one allow-listed leaf to a scalar. Hydra composes the defaults tree first (only the
    config name, the search path and group choices shape it) and then sets value overrides, so
    those keys are all that comes from the user, and the reference composition is not needed.
    A ``hydra/…`` choice, a package (``@``) or a deletion needs the reference: None."""
    from nirspi_pipe.app.validate import group_exists  # start-up: loads 15 modules of ours (27 ms here)

    keys: list[str] = []
    for ov in fixed:
        key = ov.key_or_group
        if ov.is_delete() or ov.package is not None or key == "hydra" or key.startswith("hydra/"):
            return None
        if group_exists(key):
            continue  # a trusted option file (its name is checked to exist: validate.check_overrides)
        if ov.is_add() or ov.is_force_add() or group_exists(key.split("/", 1)[0]):
            return None
        if key.startswith("hydra."):
            leaf = key[len("hydra.") :]
            kind = kind_of(leaf)
            if kind is None or kind == "searchpath" or isinstance(ov.value(), (dict, list)):
                return None
            keys.append(leaf)
    return keys


def _check_composed(
    cfg: Any, flags: dict[str, str | None], plain_keys: list[str] | None = None
) -> list[tuple[str, str]]:
    """One composed configuration: Hydra's node against the allow-list, every target, the job's
    keys and stage nodes, and (``-m``) the sweep settings. Returns the sweeper's params.
    ``plain_keys``: see :func:`_hydra_keys_if_plain` (then only those keys of Hydra's node are
    compared)."""
    from nirspi_pipe.app import validate  # start-up: loads 15 modules of ours (27 ms here)

    job, hydra_node = _plain(cfg)
    params = check_hydra_node(hydra_node, plain_keys)
    plan = Plan(job)  # the job part (no hydra key: the runner's check is the app's there)
    try:
        plan.check()  # each target once (targets.check_once): the job Hydra composes again is not compared again
        check_targets(hydra_node, "hydra")
    except ConfigError as exc:
        raise Refused(str(exc)) from None
    problem = validate.check_plain_keys(job) or validate.check_stage_nodes(job, plan)
    if not problem and "--multirun" in flags:
        resolved = _resolved_hydra(cfg)
        problem = validate.check_sweep_settings(resolved)
    if problem:
        raise Refused(problem)
    _check_output_paths(cfg)
    return params


def _resolved_hydra(cfg: Any) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for key in ("launcher", "sweeper"):
        try:
            out[key] = OmegaConf.to_container(cfg.hydra[key], resolve=True)
        except Exception:  # noqa: BLE001 - values only a running app has
            out[key] = OmegaConf.to_container(cfg.hydra[key], resolve=False)
    return out


def _check_output_paths(cfg: Any) -> None:
    """The job folders after resolution: ``hydra.sweep.subdir`` and ``hydra.output_subdir``
    relative and without ``..``, so nothing is written above the run or sweep folder (the check
    a job's own node gets, :func:`check_node_paths`)."""
    check_node_paths(cfg.hydra)


def _sweep_texts(
    sweeps: list[Any],
    hydra_node: dict[str, Any],
    fixed: list[str],
    config_name: str,
    user_paths: bool,
    flags: dict[str, str | None],
) -> tuple[list[str], int]:
    """Every sweep as override text: the command line's, ``hydra.sweeper.params`` and (with a
    user's config folder) the experiments'; and how many of them are the run's own (the first)."""
    params = (hydra_node.get("sweeper") or {}).get("params") or {}
    texts = [ov.input_line for ov in sweeps]
    texts += [f"{k}={v}" for k, v in params.items()]
    experiments = (hydra_node.get("sweeper") or {}).get("experiments") or []
    if experiments and user_paths:
        texts += _experiment_sweeps(experiments, fixed, config_name, flags)
    return texts, len(sweeps) + len(params)


def _check_sweep_values(
    job: dict[str, Any],
    ov: Any,
    is_group: bool,
    fixed: list[str],
    config_name: str,
    user_paths: bool,
    flags: dict[str, str | None],
) -> list[Any]:
    """Each value of one sweep checked for its key or group; the values."""
    key = ov.key_or_group
    values = _candidates(ov, group_options(key) if is_group else None) if ov.is_sweep_override() else [ov.value()]
    for value in values:
        if is_group:
            _check_group_value(ov, key, value, fixed, config_name, user_paths, flags)
        else:
            _check_key_value(job, key, value)
    return values


def _check_sweeps(
    cfg: Any,
    sweeps: list[Any],
    fixed: list[str],
    config_name: str,
    user_paths: bool,
    flags: dict[str, str | None],
) -> None:
    """Every value of every sweep (command line and ``hydra.sweeper.params``) for its key."""
    job, hydra_node = _plain(cfg)
    sweep_texts, n_own = _sweep_texts(sweeps, hydra_node, fixed, config_name, user_paths, flags)
    groups = all_groups()
    grid: list[list[str]] = []  # each swept group's key elements and values, as the jobs will set them
    for i, ov in enumerate(parse_overrides(sweep_texts)):
        key = ov.key_or_group  # Hydra's parse: no package, no +/~ prefix
        if _is_hydra_key(key):
            raise Refused(f"{ov.input_line}: sweeping Hydra's own settings is not allowed")
        if ov.is_delete():
            continue
        is_group = key in groups
        values = _check_sweep_values(job, ov, is_group, fixed, config_name, user_paths, flags)
        if is_group and i < n_own:
            grid.append([f"{ov.get_key_element()}={'null' if v is None else v}" for v in values])
    if user_paths and len(grid) > 1:
        _check_group_combinations(grid, fixed, config_name, hydra_node, flags)


#: At most this many combinations of swept config groups are composed before a sweep with a user's
#: config folder and Hydra's own sweeper and launcher (assumed: 256 compositions take about 25 s
#: at ~0.1 s each, ``nirspi-bench compose``; beyond that the nirspi launcher checks job by job).
MAX_CHECKED_COMBINATIONS = 256

#: Sweepers and launchers that compose each job and pass its Hydra node through :func:`check_job`
#: before anything of the job runs (the nirspi sweeper's :meth:`compose`, the nirspi launcher's
#: ``launch``); with Hydra's own (basic, joblib, submitit, Optuna's) the job gate in the task
#: function comes after Hydra configured the job's logging and wrote ``.hydra/``.
GATED_BEFORE_LAUNCH = frozenset(
    {
        "hydra_plugins.nirspi_pipe_sweeper.NirspiSweeper",
        "hydra_plugins.nirspi_pipe_sweeper.NirspiOptunaSweeper",
        "hydra_plugins.nirspi_pipe_sweeper.NirspiLauncher",
    }
)


def _check_group_combinations(
    grid: list[list[str]], fixed: list[str], config_name: str, hydra_node: dict[str, Any], flags: dict[str, str | None]
) -> None:
    """With a user's config folder, two swept groups can make together what neither makes alone:
    an option file's defaults list may pick an option by interpolation (``override
    /hydra/job_logging: ${metrics}``), so ``+experiment=a metrics=x`` chooses a logging config
    that ``+experiment=a`` and ``metrics=x`` each leave alone. Every combination is composed as
    the launcher will compose the job (``load_sweep_config``: Hydra's overrides, then the job's)
    and checked whole, unless the sweeper or the launcher is one of :data:`GATED_BEFORE_LAUNCH`,
    which composes and checks each job before it runs (the same compositions, done once). With
    Hydra's own pair, beyond :data:`MAX_CHECKED_COMBINATIONS` the sweep is refused."""
    targets = {str((hydra_node.get(k) or {}).get("_target_")) for k in ("sweeper", "launcher")}
    if targets & GATED_BEFORE_LAUNCH:
        return
    count = math.prod(len(values) for values in grid)
    if count > MAX_CHECKED_COMBINATIONS:
        raise Refused(
            f"a sweep of {count} combinations of config groups with a config folder of yours is checked "
            f"combination by combination before Hydra's launchers run it, at most {MAX_CHECKED_COMBINATIONS}; "
            "allowed: fewer combinations, or the nirspi sweeper or launcher (the defaults), which check each job "
            "before it starts"
        )
    for combination in itertools.product(*grid):
        _check_composed(compose_config(config_name, [*fixed, *combination]), flags)


def _experiment_sweeps(
    experiments: list[str], fixed: list[str], config_name: str, flags: dict[str, str | None]
) -> list[str]:
    """Each experiment of a meta-experiment composed (and checked) as the sweeper will compose
    it; returns the sweeps each one holds, as ``key=sweep`` texts."""
    shared = [o for o in fixed if not o.lstrip("+~").startswith("experiment=")]  # as NirspiSweeper does
    texts: list[str] = []
    for name in experiments:
        one = compose_config(config_name, [f"+experiment={name}", *shared])
        _check_composed(one, flags)
        texts += [f"{k}={v}" for k, v in ((_plain(one)[1].get("sweeper") or {}).get("params") or {}).items()]
    return texts


def _check_group_value(
    ov: Any,
    key: str,
    value: Any,
    fixed: list[str],
    config_name: str,
    user_paths: bool,
    flags: dict[str, str | None],
) -> None:
    """One option of a swept config group: a shipped or plugin option (or null/off); with a
    user's config folder the option may come from there, so the job it makes is composed and
    checked whole."""
    from nirspi_pipe.app import validate  # start-up: loads 15 modules of ours (27 ms here)

    text = "null" if value is None else str(value)
    allowed = group_options(key)
    if text not in ("null", "None", validate.OFF_OPTION) and text not in allowed and not user_paths:
        raise Refused(f"{key}={text} is not an option; allowed: {', '.join(allowed)} (or null)")
    if user_paths:  # composed as Hydra composes it: the parsed key element (+, ++, @package) kept
        _check_composed(compose_config(config_name, [*fixed, f"{ov.get_key_element()}={text}"]), flags)


def _check_key_value(job: dict[str, Any], key: str, value: Any) -> None:
    """One value of a swept key: its targets allowed, and the job with it set passing the key
    and type checks."""
    from nirspi_pipe.app import validate  # start-up: loads 15 modules of ours (27 ms here)

    try:
        if key == "_target_" or key.endswith("._target_"):
            check_target(value, key)
        else:
            check_targets(value, key)
    except ConfigError as exc:
        raise Refused(str(exc)) from None
    one = OmegaConf.create(job)
    try:
        OmegaConf.update(one, key, value, merge=False, force_add=True)
    except Exception as exc:  # noqa: BLE001 - a value that cannot be set is refused
        raise Refused(f"{key}={short_value(value)} cannot be set: {one_line(exc)}") from None
    problem = validate.check_plain_keys(OmegaConf.to_container(one, resolve=False))
    if problem:
        raise Refused(problem)
