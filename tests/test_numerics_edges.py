"""Valid inputs finish with finite, truthful numbers or are refused in one line (issue 40).

* the runner's safety net (pipeline._Clock): a numpy floating-point error, an OverflowError or a
  NaN/Inf product inside a stage fails the job with one line naming the stage, never status ok;
* ranges at float64's edge: each key that overflowed at a valid value is now refused in one line
  naming the key and the range that works, and its new bound finishes with finite numbers;
* values left out of a record carry their true reason (finite.reason_for);
* every JSON file a run and a sweep write is strict JSON (no NaN/Infinity tokens);
* every spelling an error message suggests (``.inf``, ``null``) is accepted by the command line's
  parser (the gate nirspi-run and the Python API share).
"""

from __future__ import annotations

import json
import math
import subprocess
import sys
import warnings
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from nirspi_pipe.app.api import compose
from nirspi_pipe.app.validate import hydra_floats
from nirspi_pipe.errors import ConfigError, NumericalError
from nirspi_pipe.execute import execute_job
from nirspi_pipe.finite import drop_nonfinite, reason_for
from nirspi_pipe.instantiate import plain_config
from nirspi_pipe.jobkey import config_hash
from nirspi_pipe.pipeline import _Clock, _recorded_warnings, run_pipeline
from nirspi_pipe.strictjson import decode_nonfinite, dumps_strict
from nirspi_pipe.types import Image2D

FAST = ["camera.resolution=8", "output.images=false", "output.arrays=false"]


def _strict(text: str) -> Any:
    def refuse(token: str) -> Any:
        raise ValueError(f"non-standard JSON token {token}")

    return json.loads(text, parse_constant=refuse)


def _run(tmp_path: Path, overrides: list[str]) -> dict[str, Any]:
    cfg, choices = compose([*FAST, *overrides])
    return execute_job(cfg, tmp_path, dict(choices), overrides)


# ---------------------------------------------------------------------------------------------
# The safety net
# ---------------------------------------------------------------------------------------------


def _clock_call(fn: Any) -> Any:
    with _recorded_warnings() as caught:
        return _Clock(caught).call("solver", fn)


def test_net_fails_a_stage_whose_arithmetic_overflowed() -> None:
    def overflowing() -> Image2D:
        big = np.full((4, 4), 1e300)
        return Image2D(np.clip(big * big, 0, 1))  # overflow, then clipped back to finite

    with pytest.raises(NumericalError) as exc:
        _clock_call(overflowing)
    text = str(exc.value)
    assert text.startswith("solver: ") and "overflow encountered in multiply" in text and "\n" not in text
    assert "test_numerics_edges.py" in text  # where it happened


def test_net_lets_intended_infinities_through() -> None:
    def intended() -> Image2D:
        with np.errstate(divide="ignore"):
            d = 1.0 / np.zeros(3)  # an Inf on purpose, said so with errstate
        return Image2D(np.where(np.isfinite(d), d, 0.0).reshape(1, 3))

    assert _clock_call(intended).data.shape == (1, 3)


def test_net_fails_a_nonfinite_product_and_a_python_overflow() -> None:
    with pytest.raises(NumericalError, match=r"^solver: .*Image2D.data \(1 of 4 values NaN or Inf\)"):
        _clock_call(lambda: Image2D(np.array([[0.0, 1.0], [np.inf, 2.0]])))
    with pytest.raises(NumericalError, match=r"^solver: .*OverflowError"):
        _clock_call(lambda: Image2D(np.full((1, 1), 1e200**2)))


def test_net_names_the_floating_point_error_behind_a_later_failure() -> None:
    def fails_after_overflow() -> Image2D:
        x = np.array([1e300]) * 1e300
        raise ValueError(f"bounds must be finite, got {x[0]}")

    with pytest.raises(NumericalError, match=r"^solver: .*overflow encountered in multiply.*then ValueError"):
        _clock_call(fails_after_overflow)
    with pytest.raises(KeyError):  # a failure without a floating-point error is left as it is (a bug)
        _clock_call(lambda: {}["x"])


def test_time_varying_effects_with_steps_beyond_float64_settle() -> None:
    """A correlation time far below the pattern period (Δt/τ overflows) is uncorrelated noise
    and a settled LED droop, not a floating-point error."""
    _finishes_finite(
        [
            "source.pattern_rate_hz=1e-6",
            "fog.fluctuation_rel=1",
            "fog.fluctuation_time_s=1e-300",
            "illumination.wander_rel=10",
            "illumination.wander_time_s=1e-300",
            "source.effects.led_droop_rel=1",
            "source.effects.led_droop_time_s=1e-300",
        ]
    )


def test_net_fails_a_job_end_to_end_naming_the_stage(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A reconstruction of ±1e300 (finite) used to finish 'ok' with overflow warnings in the
    scores; it now fails in one line naming the stage whose arithmetic overflowed."""
    from nirspi_pipe.solvers.fwht import FWHTSolver

    solve = FWHTSolver.solve

    def huge(self: FWHTSolver, acq: Any) -> Image2D:
        img = solve(self, acq)
        return Image2D(img.data * 1e300, info=img.info)

    monkeypatch.setattr(FWHTSolver, "solve", huge)
    rec = _run(tmp_path, [])
    assert rec["meta"]["status"] == "failed"
    assert rec["meta"]["error_type"] == "NumericalError"
    assert rec["meta"]["error"].startswith("metrics: ") and "encountered" in rec["meta"]["error"]
    _strict((tmp_path / "record.json").read_text())


# ---------------------------------------------------------------------------------------------
# Ranges at float64's edge: refused in one line naming the key, the bound itself finishes
# ---------------------------------------------------------------------------------------------

#: (override that crashed or overflowed before, the key and range the refusal names,
#:  an override at the new bound that must finish ok with finite numbers)
EDGES = [
    ("solver=lstsq solver.damp=1e300", "solver.damp=1e+300 is not allowed; allowed: a damping in [0, 1e+150]",
     "solver=lstsq solver.damp=1e150"),
    ("source.effects.noise_rel=1e300", "source.effects.noise_rel=1e+300 is not allowed; allowed: a relative noise level in [0, 1e+06]",
     "source.effects.noise_rel=1e6"),
    ("detector.budget.led_power_mw=1e-300", "detector.budget.led_power_mw=1e-300 is not allowed; allowed: a power per LED in mW in [1e-12, 1e+06]",
     "detector.budget.led_power_mw=1e-12"),
    ("detector.budget.t_int_us=1e-300", "detector.budget.t_int_us=1e-300 is not allowed; allowed: an integration time in µs in [1e-06, 1e+09]",
     "detector.budget.t_int_us=1e-6"),
    ("detector.budget.a_pix_um2=1e-300", "detector.budget.a_pix_um2=1e-300 is not allowed; allowed: an area in µm² in [1e-06, 1e+12]",
     "detector.budget.a_pix_um2=1e-6"),
    ("detector.budget.fov_half_deg=1e-300", "detector.budget.fov_half_deg=1e-300 is not allowed; allowed: a half angle in degrees in [0.001, 85]",
     "detector.budget.fov_half_deg=1e-3"),
    ("detector.budget.fill_factor=1e-300", "detector.budget.fill_factor=1e-300 is not allowed; allowed: a fraction in [1e-06, 1]",
     "detector.budget.fill_factor=1e-6 detector.budget.quantum_efficiency=1e-6 detector.budget.lens_transmittance=1e-6"),
    ("fog.piezo_frequency_hz=1e-300", "fog.piezo_frequency_hz=1e-300 is not allowed; allowed: a frequency in Hz in [1000, 1e+09]",
     "fog.piezo_frequency_hz=1e3"),
    ("fog.piezo_frequency_hz=1e300", "fog.piezo_frequency_hz=1e+300 is not allowed; allowed: a frequency in Hz in [1000, 1e+09]",
     "fog.piezo_frequency_hz=1e9"),
    ("fog.droplet_diameter_um=1e-300", "fog.droplet_diameter_um=1e-300 is not allowed; allowed: a diameter in µm in [0.001, 10000], or null",
     "fog.droplet_diameter_um=1e-3"),
    ("solver=completion solver.f0=1e-300", "solver.f0=1e-300 is not allowed; allowed: a roll-off frequency in [0.001, 1000] (cycles per image side), or null",
     "solver=completion solver.f0=1e-3 solver.alpha=6"),
    ("solver=completion solver.f0=1e300", "solver.f0=1e+300 is not allowed; allowed: a roll-off frequency in [0.001, 1000] (cycles per image side), or null",
     "solver=completion solver.f0=1e3 solver.alpha=6"),
    ("source.pattern_rate_hz=1e-300", "source.pattern_rate_hz=1e-300 is not allowed; allowed: a rate in Hz in [1e-06, 1e+12]",
     "source.pattern_rate_hz=1e-6 illumination.drift_rel_per_s=10 illumination.flicker_rel=10 illumination.flicker_hz=1e9"),
    ("illumination.flicker_hz=1e300", "illumination.flicker_hz=1e+300 is not allowed; allowed: a frequency in Hz in [0, 1e+09]",
     "source.pattern_rate_hz=1e12 illumination.flicker_rel=10 illumination.flicker_hz=1e9"),
    ("illumination.spectrum=halogen illumination.mains_hz=1e9", "illumination.mains_hz=1000000000.0 is not allowed; allowed: a mains frequency in Hz in (0, 5e+08]",
     "illumination.spectrum=halogen illumination.mains_hz=5e8 source.pattern_rate_hz=1e-6"),
    ("solver=completion solver.noise=1e300", "solver.noise=1e+300 is not allowed; allowed: auto, or a noise sigma per measurement in [0, 1e+12]",
     "solver=completion solver.noise=1e12"),
]  # fmt: skip


def _finishes_finite(overrides: list[str]) -> dict[str, float]:
    """Run ``overrides`` in-process: no RuntimeWarning, every metric finite, SSIM in [-1, 1],
    RMSE >= 0; returns the metrics."""
    cfg, _ = compose([*FAST, *overrides])
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        out = run_pipeline(plain_config(cfg))
    assert not [w for w in out.warnings if "RuntimeWarning" in w], out.warnings
    m = out.metrics
    assert m and all(math.isfinite(v) for v in m.values()), m
    assert all(-1.0 <= v <= 1.0 for k, v in m.items() if "ssim" in k) and m["rmse"] >= 0
    assert np.all(np.isfinite(out.products.image.data))
    return m


@pytest.mark.parametrize(("bad", "message", "edge"), EDGES, ids=[e[0] for e in EDGES])
def test_edge_refused_in_one_line_and_its_bound_finishes(bad: str, message: str, edge: str) -> None:
    cfg, _ = compose([*FAST, *bad.split()])
    with pytest.raises(ConfigError) as exc:
        run_pipeline(plain_config(cfg))
    assert str(exc.value) == message  # the one line nirspi-run prints and the record keeps
    _finishes_finite(edge.split())


def test_a_refused_edge_is_a_failed_record_in_one_line(tmp_path: Path) -> None:
    rec = _run(tmp_path, ["solver=lstsq", "solver.damp=1e300"])  # was OverflowError with a traceback
    assert rec["meta"]["status"] == "failed" and rec["meta"]["error_type"] == "ConfigError"
    assert rec["meta"]["error"] == EDGES[0][1]


def test_completion_with_its_guard_firing_records_no_nan(tmp_path: Path) -> None:
    """alpha=0 made the guard fall back and put neg_log_evidence=NaN into info (left out, 'not a
    finite number'); no value is computed there, so none is recorded."""
    rec = _run(tmp_path, ["solver=completion", "solver.alpha=0"])
    assert rec["meta"]["status"] == "ok"
    assert not [w for w in rec["meta"]["warnings"] if "left out of the record" in w]


# ---------------------------------------------------------------------------------------------
# True reasons for values left out
# ---------------------------------------------------------------------------------------------


def test_reasons_follow_the_value_not_the_key_suffix() -> None:
    assert "exactly" in reason_for("psnr_raw", math.inf)
    minus = reason_for("psnr_raw", -math.inf)
    assert "exactly" not in minus and "infinite" in minus
    big = reason_for("ssim_raw", math.nan, {"": 8})
    assert "smaller than 3x3" not in big and "8x8" in big
    small = reason_for("ssim_raw", math.nan, {"": 2})
    assert "smaller than 3x3" in small and "2x2" in small
    assert "smaller than 3x3" not in reason_for("upscale_ssim", math.nan, {"": 2, "upscale": 8})
    assert "overflow" in reason_for("rmse", math.inf)
    assert reason_for("iterations", math.nan) == "not a finite number"


@settings(max_examples=60, deadline=None)
@given(
    prefix=st.sampled_from(["", "upscale_", "bicubic_", "noise_"]),
    kind=st.sampled_from(["psnr", "psnr_raw", "ssim", "ssim_raw", "rmse"]),
    value=st.sampled_from([math.inf, -math.inf, math.nan]),
    side=st.integers(1, 64),
)
def test_a_reason_never_contradicts_the_value(prefix: str, kind: str, value: float, side: int) -> None:
    record = {"metrics": {prefix + kind: value}}
    (line,) = drop_nonfinite(record, {"": side, "upscale": side, "bicubic": side, "noise": side})
    assert record["metrics"] == {}
    if "exactly" in line:  # an exact match is +inf PSNR, nothing else
        assert kind.startswith("psnr") and value == math.inf
    if "smaller than 3x3" in line:  # the window reason only for an image that is that small
        assert kind.startswith("ssim") and side < 3


# ---------------------------------------------------------------------------------------------
# Strict JSON
# ---------------------------------------------------------------------------------------------


def test_dumps_strict_spells_nonfinite_floats_and_they_read_back() -> None:
    data = {"a": math.inf, "b": [-math.inf, np.float64(1.5)], "c": {"d": math.nan}}
    text = dumps_strict(data)
    back = decode_nonfinite(_strict(text))
    assert back["a"] == math.inf and back["b"] == [-math.inf, 1.5] and math.isnan(back["c"]["d"])


def test_record_with_an_infinite_config_value_is_strict_json(tmp_path: Path) -> None:
    rec = _run(tmp_path, ["fog.extent_mm=inf"])
    assert rec["meta"]["status"] == "ok"
    written = _strict((tmp_path / "record.json").read_text())
    assert written["config"]["fog"]["extent_mm"] == ".inf"
    # the config read back hashes as the job's (the folder and the derived seed do not move)
    assert config_hash(written["config"]) == written["meta"]["config_hash"]
    assert config_hash(decode_nonfinite(written["config"])) == written["meta"]["config_hash"]
    assert decode_nonfinite(written["config"])["fog"]["extent_mm"] == math.inf


@pytest.mark.slow  # a sweep through the installed nirspi-run
def test_every_json_file_of_a_small_sweep_is_strict(tmp_path: Path) -> None:
    out = tmp_path / "sweep"
    args = [
        str(Path(sys.executable).parent / "nirspi-run"), "-m", *FAST, "fog.extent_mm=350,.inf",
        f"hydra.sweep.dir={out}", "hydra.launcher.n_jobs=1",
    ]  # fmt: skip
    proc = subprocess.run(args, capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-2000:]
    files = sorted(out.rglob("*.json"))
    assert len([f for f in files if f.name == "record.json"]) == 2
    for f in files:
        _strict(f.read_text())
    import pandas as pd

    table = pd.read_parquet(out / "results.parquet")  # collect reads the spelling back as a number
    assert sorted(table["fog.extent_mm"].tolist()) == [350.0, math.inf]


# ---------------------------------------------------------------------------------------------
# Spellings the error messages suggest
# ---------------------------------------------------------------------------------------------


def test_hydra_floats_rewrites_only_yaml_nonfinite_tokens() -> None:
    assert hydra_floats("fog.extent_mm=.inf") == "fog.extent_mm=inf"
    assert hydra_floats("fog.extent_mm=350,.INF") == "fog.extent_mm=350,inf"
    assert hydra_floats("x=[1,-.inf]") == "x=[1,-inf]"
    assert hydra_floats("x=.nan") == "x=nan"
    for same in ("x=1.5", "x='.inf'", "x=choice(1,.inf)", "scene=sphere", "x=.infinity", "-m"):
        assert hydra_floats(same) == same


#: (override the message suggests, key, the value the config then holds)
SUGGESTED = [
    ("fog.extent_mm=.inf", "fog.extent_mm", math.inf),  # "a fog path length in mm > 0 (.inf for unbounded fog)"
    ("fog.extent_mm=inf", "fog.extent_mm", math.inf),
    ("fog.droplet_diameter_um=null", "fog.droplet_diameter_um", None),  # "... in (0, 10000], or null"
    ("detector.full_scale_v=null", "detector.full_scale_v", None),  # "... in (0, 1000], or null"
    ("detector.adc_bits=null", "detector.adc_bits", None),  # "an integer from 1 to 32, or null"
    ("seed=null", "seed", None),  # "an integer >= 0, or null (derived from the config)"
    ("illumination.flicker_rel=null", "illumination.flicker_rel", None),
]


@pytest.mark.parametrize(("override", "key", "value"), SUGGESTED, ids=[s[0] for s in SUGGESTED])
def test_every_suggested_spelling_is_accepted(override: str, key: str, value: Any) -> None:
    cfg, _ = compose([override])
    node: Any = plain_config(cfg)
    for part in key.split("."):
        node = node[part]
    assert node == value


def test_suggested_spellings_of_solver_keys_are_accepted() -> None:
    for overrides, key in (
        (["solver=lstsq", "solver.iter_lim=null"], "iter_lim"),
        (["solver=completion", "solver.f0=null"], "f0"),
    ):
        cfg, _ = compose(overrides)
        assert plain_config(cfg)["solver"][key] is None
        run_pipeline(plain_config(compose([*FAST, *overrides])[0]))  # and it runs


def test_extent_inf_runs_through_the_runner() -> None:
    cfg, _ = compose([*FAST, "fog.extent_mm=.inf"])
    out = run_pipeline(plain_config(cfg))
    assert all(math.isfinite(v) for v in out.metrics.values())


def test_config_error_message_of_extent_names_a_spelling_that_works() -> None:
    cfg, _ = compose([*FAST, "fog.extent_mm=0"])
    with pytest.raises(ConfigError, match=r"\.inf for unbounded fog"):
        run_pipeline(plain_config(cfg))
