"""Table 2: the builder on simulated acquisitions, and the experiment through the CLI."""

from __future__ import annotations

import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from nirspi_pipe.physics.detector import Photodiode
from nirspi_pipe.physics.effects import forward_model
from nirspi_pipe.physics.fog import MieFog
from nirspi_pipe.physics.range_model import paper_table2
from nirspi_pipe.scene.shapes import Plane
from nirspi_pipe.sources.simulator import Simulator
from nirspi_pipe.tables.table2 import build, lsm_max_distance
from nirspi_pipe.types import Camera


def test_lsm_recovers_a_known_law():
    z = np.linspace(0.15, 0.5, 8)
    beta, a = 1.5, np.log(3e4)
    s = np.exp(a - 2 * beta * z) / z**2
    sigma = np.sqrt(400.0**2 + 0.5 * s)
    z_max, fit = lsm_max_distance(z, s, sigma, 64)
    assert fit["beta_fit_per_m"] == pytest.approx(beta)
    s_at = np.exp(a - 2 * beta * z_max) / z_max**2
    assert s_at / 64 == pytest.approx(np.sqrt(400.0**2 + 0.5 * s_at), rel=1e-6)


@pytest.fixture(scope="module")
def frame():
    """A small Table 2 sweep run in-process (the experiment's jobs, fewer distances)."""
    rows = []
    det, fog = Photodiode(), MieFog()
    cam = Camera(16)
    seed = 0
    for fog_name, fog_model in (("none", None), ("chamber", fog)):
        for refl in (0.2, 0.5, 0.8):
            for dist in (200, 250, 300, 350, 400, 450, 500):
                sim = Simulator(forward_model(fog=fog_model, detector=det))
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    acq = sim.acquire(
                        Plane(distance_mm=dist, reflectance=refl).render(cam),
                        np.arange(256),
                        16,
                        np.random.default_rng(seed),
                    )
                seed += 1
                row = {"status": "ok", "fog": fog_name, "scene.reflectance": refl, "scene.distance_mm": float(dist)}
                row.update({f"derived.{k}": v for k, v in acq.derived.items()})
                rows.append(row)
    return pd.DataFrame(rows)


def test_table2_builder(frame, tmp_path):
    table = build(frame, tmp_path)
    for name in ("table2.csv", "table2.md", "table2_fit.png", "figure6_contrast.png"):
        assert (tmp_path / name).is_file()
    paper = paper_table2()
    for refl in (0.2, 0.5, 0.8):
        for row in ("theory_no_fog", "theory_fog"):
            assert table.loc[row, f"R={refl} (cm)"] == pytest.approx(100 * paper[row][refl], rel=0.05)
        for row in ("measured_no_fog", "measured_fog"):  # predictions from noisy simulated data
            assert table.loc[row, f"R={refl} (cm)"] == pytest.approx(100 * paper[row][refl], rel=0.10)
    assert (table.filter(like="diff").abs().to_numpy()[:2] <= 5.0).all()
    back = pd.read_csv(tmp_path / "table2.csv", index_col="row")
    assert list(back.index) == ["theory_no_fog", "theory_fog", "measured_no_fog", "measured_fog"]
    assert "calibration cells" in (tmp_path / "table2.md").read_text()


def test_table2_builder_names_missing_columns(tmp_path):
    with pytest.raises(ValueError, match="experiment=table2"):
        build(pd.DataFrame({"status": ["ok"]}), tmp_path)


@pytest.mark.slow
def test_table2_experiment_through_the_cli(tmp_path):
    exe = Path(sys.executable).with_name("nirspi-run")
    sweep = tmp_path / "t2"
    cmd = [
        str(exe),
        "-m",
        "+experiment=table2",
        f"hydra.sweep.dir={sweep}",
        "scene.reflectance=0.5",
        "scene.distance_mm=250,300,400",
    ]
    res = subprocess.run(cmd, capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert res.returncode == 0, res.stderr[-2000:]
    table = pd.read_csv(sweep / "tables" / "table2.csv", index_col="row")
    assert table.loc["theory_no_fog", "R=0.5 (cm)"] == pytest.approx(35.0, rel=1e-3)
    assert table.loc["theory_fog", "R=0.5 (cm)"] == pytest.approx(27.0, rel=0.05)
    assert np.isfinite(table.loc["measured_fog", "R=0.5 (cm)"])
    assert (sweep / "tables" / "figure6_contrast.png").is_file()


def test_beta_fit_inside_the_chamber_recovers_the_extinction():
    """A noise-free board signal with fog filling min(z, 35 cm): the fit inside the chamber returns
    β exactly; the paper's all-distance line (15-50 cm) underestimates it."""
    import numpy as np
    import pandas as pd

    from nirspi_pipe.tables.table2 import _chamber_fit, lsm_max_distance

    beta = 1.149
    z = np.arange(150, 501, 50, dtype=float)
    s = 1e6 * np.exp(-2 * beta * np.minimum(z * 1e-3, 0.35)) / (z * 1e-3) ** 2
    good = pd.DataFrame({"scene.distance_mm": z, "derived.measured_signal_e": s})
    fit = _chamber_fit(good)
    assert fit["n"] == 5 and fit["extent_m"] == pytest.approx(0.35)
    assert fit["beta_fit_per_m"] == pytest.approx(beta, rel=1e-9)
    _, all_fit = lsm_max_distance(z * 1e-3, s, np.full(z.shape, 30.0), 64)
    assert all_fit["beta_fit_per_m"] < 0.8 * beta
