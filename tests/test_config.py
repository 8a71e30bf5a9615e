"""Every option of every config group composes and instantiates; bad values name their key."""

from __future__ import annotations

import dataclasses
import functools

import pytest
from hydra import compose, initialize_config_module
from omegaconf import OmegaConf

from nirspi_pipe.app.validate import check_overrides, config_groups, group_options
from nirspi_pipe.errors import ConfigError
from nirspi_pipe.pipeline import STAGE_GROUPS, build

CONFIG_MODULE = "nirspi_pipe.conf"


def _options() -> list[tuple[str, str]]:
    return [(g, o) for g in config_groups() for o in group_options(g) if g != "experiment"]


def _compose(overrides: list[str]):
    with initialize_config_module(CONFIG_MODULE, version_base="1.3"):
        return compose("config", overrides=overrides)


@functools.cache
def _default_groups() -> frozenset[str]:
    """Groups chosen in the primary config's defaults list (the others, e.g. preset and the
    scan-order study's mechanism, are appended with +group=option)."""
    with initialize_config_module(CONFIG_MODULE, version_base="1.3"):
        return frozenset(compose("config", return_hydra_config=True).hydra.runtime.choices)


def _select(group: str, option: str) -> str:
    return f"{group}={option}" if group in _default_groups() else f"+{group}={option}"


def test_groups_are_discovered() -> None:
    groups = config_groups()
    for g in ("scene", "source", "scan", "solver", "metrics"):
        assert g in groups
        assert group_options(g), f"group {g} has no options"


@pytest.mark.parametrize(("group", "option"), _options())
def test_every_option_composes_and_instantiates(group: str, option: str) -> None:
    cfg = _compose([_select(group, option)])
    node = cfg.get(group)
    if node is None:  # an explicit "off" option
        return
    OmegaConf.resolve(cfg)
    if "_target_" not in node:
        pytest.skip(f"{group}={option} has no _target_ (a parameter-only node)")
    try:
        stage = build(node, group)
    except ConfigError as exc:
        # Options that need user input (a file: scene.path, source.path; a device: source.port)
        # may refuse their placeholder, and must say so by naming that key.
        assert exc.key.endswith((".path", ".port")), exc
        return
    assert stage is not None


def test_experiments_compose() -> None:
    for exp in group_options("experiment") if "experiment" in config_groups() else []:
        cfg = _compose([f"+experiment={exp}"])
        assert cfg is not None


def test_default_config_has_null_optional_stages() -> None:
    """The default is the paper's 2D device: FSRCNN x4 on, the 3D stages off; preset=null drops
    the super-resolution too (the 64² study)."""
    cfg = _compose([])
    assert cfg.camera.resolution == 8 and cfg.upscale.scale == 4
    for g in ("sfs", "itof", "fusion", "surface"):
        assert cfg.get(g) is None
    study = _compose(["preset=off"])
    assert study.camera.resolution == 64
    for g in ("upscale", "sfs", "itof", "fusion", "surface"):
        assert study.get(g) is None
    assert set(STAGE_GROUPS) >= {"scene", "source", "scan", "solver", "metrics"}


@pytest.mark.parametrize(
    ("override", "key"),
    [
        ("scene.distance_mm=-1", "scene.distance_mm"),
        ("scene.reflectance=1.5", "scene.reflectance"),
        ("scene.reflectance=-0.1", "scene.reflectance"),
        ("camera.resolution=100", "camera.resolution"),
        ("camera.resolution=0", "camera.resolution"),
        ("scan.ratio=0", "scan.ratio"),
        ("scan.ratio=1.5", "scan.ratio"),
        ("source.effects.noise_rel=-1", "source.effects.noise_rel"),
    ],
)
def test_out_of_range_values_name_their_key(override: str, key: str) -> None:
    cfg = _compose([override])
    group = key.split(".")[0]
    with pytest.raises(ConfigError) as info:
        build(cfg[group], group)
    assert info.value.key == key
    assert key in str(info.value) and "allowed" in str(info.value)


def test_unknown_options_and_keys_are_one_line() -> None:
    msg = check_overrides(["scan=nope"])
    assert msg is not None and "scan=nope" in msg and "basic" in msg and "\n" not in msg
    msg = check_overrides(["-m", "seed=0,1", "solver=fwht,bogus"])
    assert msg is not None and "solver=bogus" in msg
    msg = check_overrides(["scene.diameterr_mm=3"])
    assert msg is not None and "scene.diameterr_mm" in msg and "diameter_mm" in msg
    assert check_overrides(["scan=basic", "seed=3", "scene.diameter_mm=30"]) is None
    assert check_overrides(["+scene.extra=1"]) is None  # additions are Hydra's business


@pytest.mark.parametrize(
    ("overrides", "key", "allowed"),
    [
        (["scene.distance_mm=abc"], "scene.distance_mm", "a number"),
        (["fog=chamber", "fog.number_density_per_cm3=lots"], "fog.number_density_per_cm3", "a number"),
        (["fog=chamber", "fog.droplet_diameter_um=lots"], "fog.droplet_diameter_um", "a number, or null"),
        (
            ["fog=measured", "fog.beta_per_m=-1"],
            "fog.beta_per_m",
            "an extinction coefficient",
        ),  # a value: the stage's words
        (["camera.resolution=abc"], "camera.resolution", "an integer"),
        (["camera.resolution=7"], "camera.resolution", "a power of two"),
        (["illumination=klux", "illumination.klux=true"], "illumination.klux", "a number"),
        (["source.effects.noise_rel=abc"], "source.effects.noise_rel", "a number"),
    ],
)
def test_a_wrong_type_names_the_annotated_type(overrides: list[str], key: str, allowed: str) -> None:
    """A wrong type is judged from the annotation (no stage is built to borrow its words); a
    value of the right type by the stage's own range check."""
    from nirspi_pipe.pipeline import run_pipeline

    with pytest.raises(ConfigError) as info:
        run_pipeline(_compose([*overrides, "camera.resolution=8"] if "camera" not in key else overrides))
    assert info.value.key == key and info.value.allowed.startswith(allowed)
    assert str(info.value).startswith(f"{key}=") and "\n" not in str(info.value)


@dataclasses.dataclass(frozen=True)
class _Unreadable:
    """A target whose annotation names a type that does not exist (test only)."""

    x: NoSuchType = 1  # type: ignore[name-defined]  # noqa: F821


def test_check_types_does_not_swallow_an_unreadable_target(monkeypatch: pytest.MonkeyPatch) -> None:
    from nirspi_pipe import targets
    from nirspi_pipe.instantiate import check_types

    target = f"{__name__}._Unreadable"
    monkeypatch.setattr(targets, "PROJECT_TARGETS", targets.PROJECT_TARGETS | {target})
    with pytest.raises(TypeError, match=f"scene._target_={target}: its annotations cannot be read: .*NoSuchType"):
        check_types({"_target_": target, "x": 2}, "scene")


def test_a_top_level_typo_suggests_the_nearest_key() -> None:
    msg = check_overrides(["scen.distance_mm=1"])
    assert msg is not None and "did you mean scene.distance_mm?" in msg
    assert "\n" not in msg


def test_null_becomes_the_off_option_and_required_groups_refuse_it() -> None:
    from nirspi_pipe.app.validate import OFF_OPTION, REQUIRED_GROUPS, rewrite_nulls

    args, problem = rewrite_nulls(["-m", "upscale=null,bicubic", "sfs=None", "seed=0", "scene.distance_mm=null"])
    assert problem is None
    assert args == ["-m", f"upscale={OFF_OPTION},bicubic", f"sfs={OFF_OPTION}", "seed=0", "scene.distance_mm=null"]
    for group in REQUIRED_GROUPS:
        _, problem = rewrite_nulls([f"{group}=null"])
        assert problem is not None and problem.startswith(f"{group}=null is not allowed") and "allowed:" in problem
    for group in (
        "scene",
        "fog",
        "illumination",
        "detector",
        "upscale",
        "sfs",
        "itof",
        "fusion",
        "surface",
        "metrics",
        "preset",
    ):
        assert OFF_OPTION in group_options(group), group
        assert _compose([f"{group}={OFF_OPTION}"]).get(group) is None


@pytest.mark.slow  # five nirspi-run starts
def test_stage_null_on_the_command_line_runs(cli) -> None:
    for args in (["sfs=null"], ["metrics=null"], ["fusion=null"]):
        res = cli("nirspi-run", *args, "camera.resolution=8", "output.quiet=true", "hydra.run.dir=out")
        assert res.returncode == 0, (args, res.stderr[-2000:])
    # the simulated camera's models are not stages: their "nothing" is an option, null a one-line hint
    for arg, hint in (("fog=null", "fog=none (clear air)"), ("detector=off", "detector=ideal (noise-free)")):
        res = cli("nirspi-run", arg, "camera.resolution=8", "output.quiet=true", "hydra.run.dir=out")
        assert res.returncode == 2 and res.stderr.strip().splitlines()[-1].endswith(
            f"allowed: {hint}; {arg.split('=')[0]} is a model of the simulated camera, not a stage"
        ), res.stderr[-2000:]
    res = cli("nirspi-run", "solver=null", "hydra.run.dir=out")
    assert res.returncode == 2 and "solver=null is not allowed" in res.stderr
    res = cli("nirspi-run", "scene=null", "camera.resolution=8", "hydra.run.dir=out")
    assert res.returncode == 2 and res.stderr.strip().endswith("a scene (this source simulates one)")
