"""What a user may change in Hydra's own node (``hydra.*``): the allow-list, as data (issue 32).

:func:`nirspi_pipe.app.entry.check_invocation` composes the configuration twice, once as the user
asked (overrides, ``-cd``, ``-cn``, experiment files) and once with nothing of the user's but
the ``hydra/…`` group choices, and compares the two ``hydra`` nodes leaf by leaf. A leaf that
differs must match a pattern of :data:`HYDRA_KEYS` and pass the check its kind names; anything
else (logging handlers given inline, callbacks, ``job.env_set``, ``searchpath`` entries that are
not folders, ``output_subdir`` other than null or ``.hydra``, launcher options not listed here)
is refused with one line. A ``hydra/<group>`` choice may differ from the default only for the
groups of :data:`HYDRA_CHOICE_GROUPS`, and only for an option that exists on the default search
path (Hydra's own configs, nirspi-pipe's and installed plugins'): a ``-cd`` folder cannot add one.

Patterns are dotted keys below ``hydra.``; ``*`` stands for one key, a trailing ``**`` for any
number (at least one). This module imports nothing heavy: it is data.
"""

from __future__ import annotations

__all__ = [
    "HYDRA_CHOICE_GROUPS",
    "HYDRA_KEYS",
    "IGNORED_KEYS",
    "OPTUNA_SWEEPER",
    "OPTUNA_TARGET_PREFIXES",
    "LOGGING_PRESETS_NOTE",
    "REFUSED_HYDRA_CHOICES",
]

#: ``hydra/<group>`` choices a user may change (to an option on the default search path).
#: ``job_logging``/``hydra_logging``: Hydra's own presets (default, disabled, none, stdout,
#: hydra_debug) and any nirspi-pipe ships; never a node given inline (that is a leaf change).
HYDRA_CHOICE_GROUPS: frozenset[str] = frozenset(
    {
        "hydra/launcher",
        "hydra/sweeper",
        "hydra/sweeper/sampler",  # hydra-optuna-sweeper (issue 34)
        "hydra/job_logging",
        "hydra/hydra_logging",
        "hydra/help",
        "hydra/hydra_help",
    }
)

#: ``hydra/<group>=<option>`` choices that exist but are refused, with the reason (one line).
REFUSED_HYDRA_CHOICES: dict[tuple[str, str], str] = {
    # optuna 2.10's GridSampler calls Study.stop() once its grid is used up; outside
    # Study.optimize (the plugin asks and tells) that raises, so the sweep ends in a traceback
    ("hydra/sweeper/sampler", "grid"): (
        "optuna 2.10's grid sampler stops the study from outside an objective, which the Hydra plugin "
        "turns into a crash; for a grid use nirspi's own sweeper (a plain -m sweep, docs/sweeps.md)"
    ),
}

LOGGING_PRESETS_NOTE = "a preset among Hydra's and nirspi-pipe's (hydra/job_logging=disabled), never given inline"

#: Leaves of the ``hydra`` node that Hydra fills itself or that only describe the invocation:
#: not compared.
IGNORED_KEYS: tuple[str, ...] = ("runtime.**", "overrides.**", "job.config_name", "job.override_dirname")

#: ``{pattern: kind}``; the kinds are checked in :mod:`nirspi_pipe.app.hydranode` (``_KIND_CHECKS``):
#:
#: * ``dir``: an output folder, a non-empty string without control characters (absolute or
#:   relative: it is where the user wants the output);
#: * ``subdir``: a job folder below the sweep folder: relative, no ``..``, no interpolation but
#:   ``${hydra.job.num}``, ``${hydra.job.id}``, ``${hydra.job.name}``;
#: * ``output_subdir``: null or ``.hydra`` (Hydra's default);
#: * ``name``: a file-name-safe word (``[A-Za-z0-9_.-]``, not ``.``/``..``); ``name_or_null``;
#: * ``mode``: RUN, MULTIRUN or null; ``verbose``: true/false, a logger name or a list of them;
#: * ``bool``, ``int`` (>= 1, or -1 for n_jobs), ``int_or_null``, ``number_or_null`` (> 0),
#:   ``fraction`` (a number in [0, 1]), ``scalar`` (a number, a boolean, null or a word; never at
#:   a key starting with ``_`` such as ``_partial_``: those are instructions to Hydra's instantiate);
#: * ``sweep``: a sweep string (``a,b``, ``range(…)``, ``choice(…)``, ``interval(a,b)``,
#:   ``tag(…)``) for the key it names, checked value by value like a command-line sweep;
#: * ``experiments``: a list of options of the ``experiment`` group;
#: * ``direction``: ``minimize``/``maximize`` or a list of them;
#: * ``storage``: null, a ``postgresql``/``mysql`` URL, or ``sqlite:///`` on a file inside the sweep
#:   folder (no ``..``, no query, no link; :func:`nirspi_pipe.app.storage.check_storage`);
#: * ``optuna_target``: a class of ``optuna.samplers``/``optuna.pruners``, only with the Optuna
#:   sweeper chosen;
#: * ``searchpath``: the default entries and ``file://`` folders that exist.
HYDRA_KEYS: dict[str, str] = {
    # output folders and naming
    "run.dir": "dir",
    "sweep.dir": "dir",
    "sweep.subdir": "subdir",
    "output_subdir": "output_subdir",
    "job.name": "name",
    "verbose": "verbose",
    "mode": "mode",
    "searchpath": "searchpath",
    # the nirspi launcher (conf/hydra/launcher/nirspi.yaml) and joblib's n_jobs
    "launcher.n_jobs": "n_jobs",
    "launcher.timeout_s": "number_or_null",
    # hydra-joblib-launcher's documented numeric/simple options
    "launcher.backend": "joblib_backend",
    "launcher.prefer": "name_or_null",
    "launcher.verbose": "int_or_null",
    "launcher.timeout": "number_or_null",
    "launcher.pre_dispatch": "scalar",
    "launcher.batch_size": "scalar",
    # hydra-submitit-launcher (conf/hydra/launcher/slurm.yaml, docs/sweeps.md)
    "launcher.timeout_min": "int",
    "launcher.cpus_per_task": "int_or_null",
    "launcher.gpus_per_node": "int_or_null",
    "launcher.tasks_per_node": "int",
    "launcher.mem_gb": "number_or_null",
    "launcher.nodes": "int",
    "launcher.name": "name",
    "launcher.partition": "name_or_null",
    "launcher.qos": "name_or_null",
    "launcher.constraint": "name_or_null",
    "launcher.array_parallelism": "int",
    "launcher.additional_parameters.account": "name",
    # the nirspi sweeper (conf/hydra/sweeper/nirspi.yaml) and Hydra's basic sweeper
    "sweeper.params.**": "sweep",
    "sweeper.experiments": "experiments",
    "sweeper.resume": "bool",
    "sweeper.max_attempts": "int",
    "sweeper.allow_failures": "bool",
    "sweeper.max_batch_size": "int_or_null",
    # hydra-optuna-sweeper (issue 34): hydra/sweeper=optuna, hydra/sweeper/sampler=<tpe|random|…>
    "sweeper.n_trials": "int",
    "sweeper.n_jobs": "int",
    "sweeper.direction": "direction",
    "sweeper.study_name": "name_or_null",
    # nirspi's Optuna sweeper (hydra/sweeper=optuna, nirspi_pipe.app.study): a database
    # URL by scheme (postgresql, mysql) or SQLite inside the sweep folder; jobs per trial
    "sweeper.storage": "storage",
    "sweeper.repeats": "int",
    # the share of failed trials Optuna's sweeper, and the results callback's exit code, accept:
    # a number in [0, 1] (the plugin asserts it, with a traceback, issue 41)
    "sweeper.max_failure_rate": "fraction",
    "sweeper.sampler._target_": "optuna_target",
    "sweeper.sampler.*": "scalar",
    "sweeper.pruner._target_": "optuna_target",
    "sweeper.pruner.*": "scalar",
}

#: The Optuna sweeper's class: ``sweeper.sampler``/``sweeper.pruner`` targets only with it.
OPTUNA_SWEEPER = "hydra_plugins.nirspi_pipe_sweeper.NirspiOptunaSweeper"
#: Where an Optuna sampler's or pruner's ``_target_`` may point.
OPTUNA_TARGET_PREFIXES = {"sweeper.sampler._target_": "optuna.samplers.", "sweeper.pruner._target_": "optuna.pruners."}
#: Sampler options that name a callable or a nested object: refused even under ``sweeper.sampler.*``.
OPTUNA_REFUSED_OPTIONS = frozenset({"constraints_func", "independent_sampler", "custom_search_space", "search_space"})
