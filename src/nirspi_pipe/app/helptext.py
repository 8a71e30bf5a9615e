"""Dynamic parts of ``nirspi-run --help`` (the template is ``conf/hydra/help/nirspi.yaml``).

The config groups and their options (plugins' included), the experiments with a one-line
description each and the installed plugins come from the OmegaConf resolver ``nirspi_help``
registered here (``${nirspi_help:groups}``, ``${nirspi_help:experiments}``,
``${nirspi_help:plugins}``), and so does the camera of the composed config
(``${nirspi_help:camera}``: resolution, solver, upscaler, as ``--help`` with the same overrides
would run them). A resolver never raises: a help page must always print.

``groups`` replaces Hydra's ``$APP_CONFIG_GROUPS``, which lists every folder on the config search
path: the experiments package's data folders (``reference/ci``: the CI reference's tolerances;
``heldout``, ``mesh``, ``shapes``: scripts) looked like groups there, and ``mechanism`` (used by
``+experiment=scan_order`` only) like a stage (issue 34).
"""

from __future__ import annotations

from importlib import resources
from typing import Any

__all__ = ["RESOLVER", "camera_text", "experiments_text", "groups_text", "plugins_text", "register_resolvers"]

RESOLVER = "nirspi_help"

#: Groups that only an experiment selects: group -> the experiment that sweeps it.
EXPERIMENT_GROUPS = {"mechanism": "scan_order"}
#: Folders of the experiments package that hold data, not options: never listed as groups.
DATA_FOLDERS = frozenset({"reference", "heldout", "mesh", "shapes"})


def groups_text() -> str:
    """``group: option, …`` per top-level config group that a run selects (plugins' included),
    then those only an experiment sweeps; ``experiment`` has its own section."""
    try:
        # start-up: loads hydra, hydra_plugins (292 ms here)
        from nirspi_pipe.app.configs import (
            config_groups,
            group_options,
        )

        groups = [g for g in config_groups() if g not in DATA_FOLDERS and g != "experiment" and group_options(g)]
    except Exception as exc:  # noqa: BLE001 - help must print
        return f"(config groups could not be listed: {exc})"
    lines = [f"{g}: {', '.join(group_options(g))}" for g in groups if g not in EXPERIMENT_GROUPS]
    for g in groups:
        if g in EXPERIMENT_GROUPS:
            lines.append(
                f"{g} (only with +experiment={EXPERIMENT_GROUPS[g]}, which sweeps it): {', '.join(group_options(g))}"
            )
    return "\n".join(lines) + "\n"  # a blank line before the template's next paragraph


def _description(name: str, group: str = "experiment", package: str = "nirspi_pipe.experiments") -> str:
    """First comment line of a packaged option file (after ``# @package``), or ''."""
    try:
        text = (resources.files(package) / group / f"{name}.yaml").read_text()
    except (OSError, ModuleNotFoundError):
        return ""
    for line in text.splitlines():
        s = line.strip()
        if not s.startswith("#") or s.startswith("# @package"):
            if s and not s.startswith("#"):
                break
            continue
        return s.lstrip("# ").rstrip()
    return ""


def experiments_text() -> str:
    """``  name  description`` per experiment (``+experiment=NAME``), one per line."""
    try:
        from nirspi_pipe.app.validate import group_options  # start-up: loads hydra, hydra_plugins (271 ms here)

        names = group_options("experiment")
    except Exception as exc:  # noqa: BLE001 - help must print
        return f"  (experiments could not be listed: {exc})"
    if not names:
        return "  (none found)"
    width = max(len(n) for n in names)
    lines = []
    for n in names:
        d = _description(n)
        if len(d) > 96 - width:
            d = d[: 95 - width].rsplit(" ", 1)[0].rstrip(",;:(") + " …"
        d = d.rstrip(":")
        lines.append(f"  {n:<{width}}  {d}".rstrip())
    return "\n".join(lines)


def plugins_text() -> str:
    """Installed plugins (entry-point group ``nirspi_pipe.plugins``) and the options they add."""
    try:
        from nirspi_pipe.app.plugins import discover  # start-up: loads hydra, omegaconf (123 ms here)

        report = discover()
    except Exception as exc:  # noqa: BLE001 - help must print
        return f"  (plugins could not be listed: {exc})"
    lines = []
    for p in report.plugins:
        adds = "; ".join(f"{g}={', '.join(opts)}" for g, opts in sorted(p.options.items())) or "no options"
        lines.append(f"  {p.name} ({p.distribution}): {adds}")
    for f in report.failures:
        lines.append(f"  {f.name}: FAILED to load ({f.error})")
    if not lines:
        lines.append("  none installed (a plugin is a pip package; see docs/plugins.md)")
    return "\n".join(lines)


def camera_text(root: Any) -> str:
    """The composed config's camera in words: patterns, solver, upscaler (each option's first
    comment line), one per line, e.g. ``8x8 patterns (preset=device)``, ``solver=fwht: Exact
    inverse by the fast Walsh–Hadamard transform``."""
    from omegaconf import OmegaConf  # start-up: loads omegaconf, yaml (57 ms here)

    choices = OmegaConf.select(root, "hydra.runtime.choices", default=None) or {}
    n = OmegaConf.select(root, "camera.resolution", default=None)
    preset = {"off": "null"}.get(str(choices.get("preset")), choices.get("preset"))  # off.yaml is null
    lines = [f"{n}x{n} patterns" + (f" (preset={preset})" if preset else "")]
    for group in ("solver", "upscale"):
        name = choices.get(group)
        if name is None or OmegaConf.select(root, group, default=None) is None:
            lines.append(f"{group}=null: no {group} stage")
            continue
        what = _description(str(name), group, "nirspi_pipe.conf")
        what = what.split(";")[0].split(":")[0].split(" (")[0].rstrip(".")
        if group == "upscale":
            scale = OmegaConf.select(root, "upscale.scale", default=None)
            if isinstance(n, int) and isinstance(scale, int):
                what += f", x{scale} to {n * scale}x{n * scale}"
        lines.append(f"{group}={name}: {what}".rstrip(": "))
    return "\n  ".join(lines)  # the template indents the first line by 2


def _resolve(what: str, *, _root_: Any = None) -> str:
    try:
        if what == "experiments":
            return experiments_text()
        if what == "plugins":
            return plugins_text()
        if what == "camera":
            return camera_text(_root_)
        if what == "groups":
            return groups_text()
    except Exception as exc:  # noqa: BLE001 - help must print
        return f"({what} could not be described: {exc})"
    return f"(unknown help section {what!r}; allowed: camera, experiments, groups, plugins)"


def register_resolvers() -> None:
    """Register the ``nirspi_help`` resolver with OmegaConf (idempotent)."""
    from omegaconf import OmegaConf  # start-up: loads omegaconf, yaml (57 ms here)

    if not OmegaConf.has_resolver(RESOLVER):
        OmegaConf.register_new_resolver(RESOLVER, _resolve, use_cache=False)
