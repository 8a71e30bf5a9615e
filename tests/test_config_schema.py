"""One source of config defaults (issue 10, item 4): the Python signatures of the targets.

Every option file lists its generated schema (``schema/<group>/<option>``) and keeps only
``_target_`` and the values that differ from the target's defaults; the composed config still
has every key, at the Python default."""

from __future__ import annotations

import dataclasses
import inspect
from importlib import resources
from typing import Any

import pytest
from hydra import compose, initialize_config_module
from omegaconf import OmegaConf

from nirspi_pipe.app.configs import (
    CONFIG_MODULE,
    CONFIG_NAME,
    locate,
    register_schemas,
    schema_defaults,
    schema_node,
    schema_reference,
)
from nirspi_pipe.errors import ConfigError

#: Keys an option file may set to the same value as the target's default, with the reason.
#: Empty: nothing needs it today (interpolations such as ``${scene}`` differ from any default).
ALLOWED_REPEATS: dict[tuple[str, str], set[str]] = {}
#: Option files with a ``_target_`` that do not list its schema, with the reason.
SCHEMALESS = {
    # The absence of background light: its node holds only klux (the class default, 0), so the
    # resolved config of illumination=none runs, their job keys and the seeds that seed=null
    # derives from the config (Table 2) stay what they were before the schemas.
    ("illumination", "none"): {"klux"},
}


def _option_files() -> list[tuple[str, str, dict[str, Any]]]:
    root = resources.files(CONFIG_MODULE)
    out = []
    for group_dir in sorted(root.iterdir(), key=lambda e: e.name):
        if not group_dir.is_dir() or group_dir.name.startswith(("_", ".")) or group_dir.name == "hydra":
            continue
        for entry in sorted(group_dir.iterdir(), key=lambda e: e.name):
            if entry.name.endswith(".yaml"):
                raw = OmegaConf.to_container(OmegaConf.create(entry.read_text(encoding="utf-8")), resolve=False)
                out.append((group_dir.name, entry.name[: -len(".yaml")], raw))
    return out


def _same(a: Any, b: Any) -> bool:
    if isinstance(a, dict) and isinstance(b, dict):
        return a.keys() == b.keys() and all(_same(a[k], b[k]) for k in a)
    if isinstance(a, list) and isinstance(b, list):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b))
    return type(a) is type(b) and a == b


def _repeats(raw: dict[str, Any], defaults: dict[str, Any], where: str) -> list[str]:
    found = []
    for key, value in raw.items():
        if key in ("_target_", "defaults") or key not in defaults:
            continue
        if isinstance(value, dict) and isinstance(value.get("_target_"), str):
            found += _repeats(value, schema_defaults(value["_target_"]), f"{where}.{key}")
        elif _same(value, defaults[key]):
            found.append(f"{where}.{key}")
    return found


TARGETED = [(g, o, raw) for g, o, raw in _option_files() if isinstance(raw.get("_target_"), str)]


@pytest.mark.parametrize(("group", "option", "raw"), TARGETED, ids=[f"{g}/{o}" for g, o, _ in TARGETED])
def test_no_option_file_repeats_a_python_default(group: str, option: str, raw: dict[str, Any]) -> None:
    if (group, option) in SCHEMALESS:
        assert "defaults" not in raw and set(raw) - {"_target_"} == SCHEMALESS[group, option]
        return
    assert schema_reference(group, option) == (raw.get("defaults") or [None])[0], (
        f"conf/{group}/{option}.yaml: list {schema_reference(group, option)} first in its defaults"
    )
    repeats = set(_repeats(raw, schema_defaults(raw["_target_"]), group)) - {
        f"{group}.{k}" for k in ALLOWED_REPEATS.get((group, option), set())
    }
    assert not repeats, f"conf/{group}/{option}.yaml repeats the default of {sorted(repeats)}: delete the line"


@pytest.mark.parametrize(("group", "option", "raw"), TARGETED, ids=[f"{g}/{o}" for g, o, _ in TARGETED])
def test_every_key_of_an_option_file_is_a_parameter_of_its_target(group: str, option: str, raw: dict[str, Any]) -> None:
    target = locate(raw["_target_"])
    params = (  # fields marked config: False included (an option may set them: sfs=second_order)
        {f.name for f in dataclasses.fields(target) if f.init}
        if dataclasses.is_dataclass(target)
        else set(inspect.signature(target).parameters)
    )
    unknown = sorted(k for k in raw if k not in ("_target_", "defaults") and k not in params)
    assert not unknown, f"conf/{group}/{option}.yaml: {unknown} are not parameters of {raw['_target_']}"


def test_options_without_a_target_inherit_a_sibling() -> None:
    # sfs=godunov is sfs=lax_friedrichs with scheme: godunov.
    for group, option, raw in _option_files():
        if "_target_" in raw or group == "preset" or "defaults" not in raw and len(raw) == 1:
            continue
        if list(raw) == [group] or raw.get(group, "x") is None:  # the off option: `group: null`
            continue
        first = (raw.get("defaults") or [None])[0]
        assert isinstance(first, str) and not first.startswith(("/", "override")), (group, option, first)


def test_the_composed_config_has_every_key_at_its_python_default() -> None:
    from nirspi_pipe.physics.fog import MieFog
    from nirspi_pipe.types import Camera

    with initialize_config_module(CONFIG_MODULE, version_base="1.3"):
        cfg = compose(CONFIG_NAME, overrides=["preset=off", "fog=chamber", "sfs=oren_nayar", "source=simulator"])
    fog = OmegaConf.to_container(cfg.fog)
    assert isinstance(fog, dict)
    for f in dataclasses.fields(MieFog):
        assert fog[f.name] == getattr(MieFog(), f.name), f.name
    assert cfg.camera.resolution == Camera().resolution and cfg.camera.fov_deg == Camera().fov_deg
    assert "patterned" not in cfg.camera  # runner-set field: metadata={"config": False}
    assert "slope_average" not in cfg.sfs  # kept out of the schema: only sfs=second_order sets it
    assert cfg.sfs.backend == "auto" and cfg.sfs.roughness_rad == 0.3  # preset value, then the default
    assert cfg.source.effects.noise_rel == 0.0 and cfg.source.effects.fog is not None  # nested target, ${fog}


def test_a_new_python_default_reaches_the_config_without_touching_yaml(monkeypatch: pytest.MonkeyPatch) -> None:
    # The schema is generated from the signature: change the default, re-register, compose.
    from nirspi_pipe.scene import objects

    cls = objects.Sphere
    field = next(f for f in dataclasses.fields(cls) if f.name == "diameter_mm")
    monkeypatch.setattr(field, "default", 31.0)
    try:
        register_schemas(CONFIG_MODULE)
        with initialize_config_module(CONFIG_MODULE, version_base="1.3"):
            assert compose(CONFIG_NAME, overrides=["scene=sphere"]).scene.diameter_mm == 31.0
    finally:
        monkeypatch.undo()
        register_schemas(CONFIG_MODULE)
    assert schema_node("scene/sphere")["diameter_mm"] == 50.0


def test_schema_defaults_spell_every_parameter() -> None:
    from nirspi_pipe.physics.detector import Photodiode

    node = schema_defaults("nirspi_pipe.physics.detector.Photodiode")
    assert node["budget"]["_target_"] == "nirspi_pipe.physics.budget.PhotonBudget"
    assert node["budget"]["led_count"] == Photodiode().budget.led_count
    assert set(node) == {f.name for f in dataclasses.fields(Photodiode)}
    assert schema_defaults(lambda a, b=2: None) == {"a": "???", "b": 2}  # no default: required
    assert schema_defaults(lambda f=print: None) == {}  # a default no config can spell is left out
    with pytest.raises(ConfigError, match="nirspi_pipe.nope.Nope' is not allowed"):  # off the allow-list
        schema_defaults("nirspi_pipe.nope.Nope")
    assert locate("nirspi_pipe.types.Camera") is not None


@pytest.mark.parametrize(
    ("overrides", "key", "allowed", "before_the_run"),
    [
        (["scene.distance_mm=abc"], "scene.distance_mm", "allowed: a number", True),
        (["-m", "scene.distance_mm=150,abc"], "scene.distance_mm", "allowed: a number", True),
        # lam is ``float | str`` ("auto"): the string passes the type, the stage's range check names it
        (["solver=fista_tv", "solver.lam=xyz"], "solver.lam", "auto, or a TV weight >= 0", False),
    ],
)
def test_a_wrong_type_is_one_line_naming_key_and_allowed(
    overrides: list[str], key: str, allowed: str, before_the_run: bool
) -> None:
    from nirspi_pipe.app.validate import check_overrides
    from nirspi_pipe.errors import ConfigError
    from nirspi_pipe.pipeline import build

    msg = check_overrides(overrides)
    if before_the_run:  # refused before any job starts, sweep values included
        assert msg is not None and "\n" not in msg
        assert msg.startswith(f"{key}=") and allowed in msg
        return
    assert msg is None
    with initialize_config_module(CONFIG_MODULE, version_base="1.3"):
        cfg = compose(CONFIG_NAME, overrides=overrides)
    group = key.split(".")[0]
    with pytest.raises(ConfigError) as info:
        build(cfg[group], group)
    assert str(info.value).startswith(f"{key}=") and allowed in str(info.value) and "\n" not in str(info.value)
