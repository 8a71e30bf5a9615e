"""Table 2: maximum measurement distance vs reflectance, without and with fog.

Rows (cm, for R = 0.2, 0.5, 0.8):

* ``theory_no_fog`` / ``theory_fog``: Algorithm A1 (:func:`~nirspi_pipe.physics.range_model.max_distance_m`)
  for each job's configuration, as the simulator recorded it (``derived.range_max_m``).
* ``measured_no_fog`` / ``measured_fog``: the paper's "LSM" on simulated acquisitions of a flat
  board at several distances. For each (fog, R) group, from the jobs that did not saturate:

  1. signal: least squares of ``ln(S z²) = a − b z`` on the measured full-on signal ``S``
     (``derived.measured_signal_e``: readings minus the LEDs-off reference); ``b/2`` is the
     fitted extinction β;
  2. noise: least squares of the photon-transfer line ``σ² = c₀ + c₁ S/2`` on the measured
     reading noise (``derived.measured_noise_e``);
  3. the maximum distance is where the fitted patch signal ``S/led_count`` meets the fitted
     noise, as in Alg. A1.

β from the measurement itself: the fogged fit's ``b/2`` is compared with the true extinction
(``derived.beta_per_m``) twice: over all the board's distances (the paper's LSM) and over the
distances inside the fog (``z ≤`` the fog's extent, ``fog.extent_mm``, the 35 cm chamber of
:class:`~nirspi_pipe.physics.fog.MieFog` unless overridden). Beyond the extent the fog path stops
growing (the fog fills ``min(z, extent)``), so ``ln(S z²)`` flattens there and the all-distance
line underestimates β; inside the chamber the same fit measures it (``table2_beta.csv``).

Writes ``table2.csv`` (ours, the paper's values and the relative difference), ``table2.md``,
``table2_fit.png`` (the fits) and ``figure6_contrast.png`` (Koschmieder contrast vs distance,
Eq. 8, with the visibility of Eq. 9).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from nirspi_pipe.physics.fog import MieFog, koschmieder_contrast, visibility_m
from nirspi_pipe.physics.range_model import CALIBRATION_CELLS, bisect, paper_table2

__all__ = ["build", "contrast_figure", "lsm_max_distance"]

ROWS = {
    "theory_no_fog": "Theory, no fog (Alg. A1)",
    "theory_fog": "Theory, 3 µm fog (Alg. A1)",
    "measured_no_fog": "Simulated measurement, no fog (LSM)",
    "measured_fog": "Simulated measurement, 3 µm fog (LSM)",
}
REFLECTANCES = (0.2, 0.5, 0.8)


def lsm_max_distance(
    z_m: np.ndarray, signal_e: np.ndarray, noise_e: np.ndarray, led_count: int
) -> tuple[float, dict[str, float]]:
    """LSM estimate of the maximum distance (m) from measured signals and noises at ``z_m``.

    Returns the distance and the fit parameters (``a``, ``b``, ``beta_fit_per_m``, ``c0``, ``c1``).
    Needs at least two distances with a positive signal.
    """
    z = np.asarray(z_m, dtype=np.float64)
    s = np.asarray(signal_e, dtype=np.float64)
    sig = np.asarray(noise_e, dtype=np.float64)
    ok = np.isfinite(z) & np.isfinite(s) & np.isfinite(sig) & (s > 0) & (z > 0)
    z, s, sig = z[ok], s[ok], sig[ok]
    if z.size < 2:
        raise ValueError("the LSM needs at least two distances with a measured signal")
    slope, a = np.polyfit(z, np.log(s * z * z), 1)
    b = -slope
    # noise variance = floor + shot noise, sigma² = c0 + c1·s/2, with c0 > 0 and c1 >= 0: a line fitted
    # to noisy variances can slope down (seen at R = 0.8 without fog), and its variance then turns
    # negative at the near distances the fit and the plot extrapolate to; the best c1 >= 0 is then 0
    c1, c0 = np.polyfit(0.5 * s, sig * sig, 1) if z.size >= 2 else (0.0, float(np.mean(sig**2)))
    if c1 < 0:
        c0, c1 = float(np.mean(sig**2)), 0.0
    if c0 <= 0:  # the noise floor must be positive; fall back to the smallest measured noise
        c0, c1 = float(np.min(sig) ** 2), 0.0

    def s_fit(zz: float) -> float:
        return float(np.exp(a - b * zz) / (zz * zz))

    def excess(zz: float) -> float:
        sf = s_fit(zz)
        return np.log(sf / led_count) - 0.5 * np.log(max(c0 + c1 * 0.5 * sf, 1e-300))

    lo, hi = 1e-3, 10.0
    if excess(hi) > 0:
        z_max = hi
    elif excess(lo) < 0:
        z_max = lo
    else:
        z_max = bisect(excess, lo, hi, xtol=1e-9)
    return z_max, {"a": float(a), "b": float(b), "beta_fit_per_m": float(b / 2), "c0": float(c0), "c1": float(c1)}


def _fog_flag(frame: pd.DataFrame) -> pd.Series:
    if "fog" in frame:
        return frame["fog"].fillna("none").astype(str) != "none"
    return frame.get("derived.beta_per_m", pd.Series(0.0, index=frame.index)).fillna(0.0) > 0


_NEEDED = (
    "scene.reflectance",
    "scene.distance_mm",
    "derived.measured_signal_e",
    "derived.measured_noise_e",
    "derived.range_max_m",
)


def _group_fit(g: pd.DataFrame, good: pd.DataFrame) -> tuple[float, dict] | None:
    """One (fog, reflectance) group's LSM maximum distance and its fits, from its unsaturated
    runs ``good``; None where the fit fails."""
    led = int(good.get("derived.led_count", pd.Series([64])).iloc[0]) if len(good) else 64
    try:
        z_max, fit = lsm_max_distance(
            good["scene.distance_mm"].to_numpy() * 1e-3,
            good["derived.measured_signal_e"].to_numpy(),
            good["derived.measured_noise_e"].to_numpy(),
            led,
        )
    except ValueError:
        return None
    return z_max, {
        "chamber": _chamber_fit(good),
        "fit": fit,
        "data": good,
        "led": led,
        "beta": float(g["derived.beta_per_m"].median()),
    }


def _our_rows(df: pd.DataFrame) -> tuple[dict[str, dict[float, float]], dict[tuple[bool, float], dict]]:
    """Our maximum distances per row and reflectance (theory and the LSM fit), and the fits by
    (fogged, reflectance)."""
    sat = df.get("derived.saturated_patterns", pd.Series(0, index=df.index)).fillna(0)
    ours: dict[str, dict[float, float]] = {r: {} for r in ROWS}
    fits: dict[tuple[bool, float], dict] = {}
    for fogged in (False, True):
        tag = "fog" if fogged else "no_fog"
        for refl in REFLECTANCES:
            g = df[(df["fogged"] == fogged) & np.isclose(df["scene.reflectance"], refl)]
            if g.empty:
                continue
            ours[f"theory_{tag}"][refl] = float(np.median(g["derived.range_max_m"]))
            found = _group_fit(g, g[sat.loc[g.index] == 0])
            if found is None:
                continue
            ours[f"measured_{tag}"][refl], fits[(fogged, refl)] = found
    return ours, fits


def _comparison(ours: dict[str, dict[float, float]]) -> pd.DataFrame:
    """Table 2: our rows (cm), the paper's, and the difference (%)."""
    paper = paper_table2()
    cols: dict[str, list[float]] = {}
    for refl in REFLECTANCES:
        cols[f"R={refl} (cm)"] = [round(100 * ours[r].get(refl, np.nan), 2) for r in ROWS]
    for refl in REFLECTANCES:
        cols[f"paper R={refl} (cm)"] = [100 * paper[r][refl] for r in ROWS]
    for refl in REFLECTANCES:
        cols[f"diff R={refl} (%)"] = [
            round(100 * (ours[r].get(refl, np.nan) - paper[r][refl]) / paper[r][refl], 2) for r in ROWS
        ]
    return pd.DataFrame(cols, index=pd.Index(list(ROWS), name="row"))


def _write_betas(fits: dict[tuple[bool, float], dict], path: Path) -> None:
    """``table2_beta.csv``: the true and fitted extinction per (fog, reflectance)."""
    pd.DataFrame(
        [
            {
                "fog": fogged,
                "reflectance": refl,
                "beta_true_per_m": v["beta"],
                "beta_fit_all_per_m": v["fit"]["beta_fit_per_m"],
                "beta_fit_chamber_per_m": v["chamber"]["beta_fit_per_m"],
                "chamber_distances": v["chamber"]["n"],
                "extent_m": v["chamber"]["extent_m"],
            }
            for (fogged, refl), v in sorted(fits.items())
        ]
    ).to_csv(path, index=False, float_format="%.6g")


def build(frame: pd.DataFrame, out_dir: Path) -> pd.DataFrame:
    """Build Table 2 from a sweep's results into ``out_dir`` (see the module docstring)."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    missing = [c for c in _NEEDED if c not in frame]
    if missing:
        raise ValueError(f"table2 needs columns {missing}: run `nirspi-run -m +experiment=table2`")
    df = frame[frame["status"] == "ok"].copy() if "status" in frame else frame.copy()
    df["fogged"] = _fog_flag(df)
    ours, fits = _our_rows(df)
    table = _comparison(ours)
    table.to_csv(out_dir / "table2.csv")
    (out_dir / "table2.md").write_text(_markdown(table, fits))
    _write_betas(fits, out_dir / "table2_beta.csv")
    _plot_fits(fits, out_dir / "table2_fit.png")
    betas = sorted({round(v["beta"], 6) for v in fits.values() if v["beta"] > 0})
    _plot_contrast(betas[0] if betas else None, out_dir / "figure6_contrast.png")
    return table


def _extent_m(frame: pd.DataFrame) -> float:
    """The fog's extent (m): the ``fog.extent_mm`` column when the sweep set it, else MieFog's
    default (the 35 cm chamber)."""
    if "fog.extent_mm" in frame.columns and frame["fog.extent_mm"].notna().any():
        return float(frame["fog.extent_mm"].dropna().iloc[0]) * 1e-3
    return float(MieFog.extent_mm) * 1e-3


def _chamber_fit(good: pd.DataFrame) -> dict[str, float]:
    """``b/2`` of ``ln(S z²) = a − b z`` over the distances inside the fog's extent (NaN with fewer
    than two), the extent (m) and the number of distances used."""
    z = good["scene.distance_mm"].to_numpy(dtype=np.float64) * 1e-3
    s = good["derived.measured_signal_e"].to_numpy(dtype=np.float64)
    ext = _extent_m(good)
    ok = np.isfinite(z) & np.isfinite(s) & (s > 0) & (z <= ext + 1e-9)
    if ok.sum() < 2:
        return {"beta_fit_per_m": np.nan, "extent_m": ext, "n": int(ok.sum())}
    slope, _ = np.polyfit(z[ok], np.log(s[ok] * z[ok] ** 2), 1)
    return {"beta_fit_per_m": float(-slope / 2), "extent_m": ext, "n": int(ok.sum())}


def _markdown(table: pd.DataFrame, fits: dict) -> str:
    cal = {(row, refl) for row, refl in CALIBRATION_CELLS}
    lines = [
        "# Table 2: maximum measurement distance (cm)",
        "",
        "Each cell: ours (paper, relative difference). `*` marks the two calibration cells "
        "(docs/physics.md, 'Calibration'); every other cell is a prediction.",
        "",
        "| | " + " | ".join(f"R = {r}" for r in REFLECTANCES) + " |",
        "|---|" + "---:|" * len(REFLECTANCES),
    ]
    for row, label in ROWS.items():
        cells = []
        for refl in REFLECTANCES:
            v, p, d = (
                table.loc[row, f"R={refl} (cm)"],
                table.loc[row, f"paper R={refl} (cm)"],
                table.loc[row, f"diff R={refl} (%)"],
            )
            mark = "*" if (row, refl) in cal else ""
            cells.append("n/a" if not np.isfinite(v) else f"{v:.1f}{mark} ({p:g}, {d:+.1f} %)")
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    theory = table.loc[["theory_no_fog", "theory_fog"], [f"diff R={r} (%)" for r in REFLECTANCES]].abs().to_numpy()
    if np.isfinite(theory).all():
        lines += ["", f"Largest theory difference: {np.nanmax(theory):.1f} % (target: within 5 %)."]
    fogfits = [(refl, v) for (fogged, refl), v in sorted(fits.items()) if fogged]
    if fogfits:
        lines += [
            "",
            "LSM fit of the fogged signal, `ln(S z²) = a − 2β z`: "
            + ", ".join(
                f"R = {refl}: β_fit = {v['fit']['beta_fit_per_m']:.3f} /m (true {v['beta']:.3f} /m)"
                for refl, v in fogfits
            )
            + ".",
            "The same fit over the distances inside the fog (z ≤ "
            f"{100 * fogfits[0][1]['chamber']['extent_m']:.0f} cm, where the fog path grows with z): "
            + ", ".join(
                f"R = {refl}: β_fit = {v['chamber']['beta_fit_per_m']:.3f} /m "
                f"({100 * (v['chamber']['beta_fit_per_m'] / v['beta'] - 1):+.1f} %, {v['chamber']['n']} distances)"
                for refl, v in fogfits
            )
            + ". Beyond the chamber the fog path stops growing, so the all-distance line underestimates β.",
        ]
    return "\n".join(lines) + "\n"


def _plot_fits(fits: dict, path: Path) -> None:
    import matplotlib  # start-up: loads matplotlib, PIL, cycler (78 ms here)

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # start-up: loads matplotlib, PIL, cycler (298 ms here)

    fig, axes = plt.subplots(1, 2, figsize=(10, 4), sharey=True)
    for (fogged, refl), v in sorted(fits.items()):
        ax = axes[int(fogged)]
        d = v["data"]
        z = d["scene.distance_mm"].to_numpy() * 1e-3
        s = d["derived.measured_signal_e"].to_numpy() / v["led"]
        zz = np.linspace(0.05, 0.6, 200)
        f = v["fit"]
        sf = np.exp(f["a"] - f["b"] * zz) / zz**2
        line = ax.plot(zz * 100, sf / v["led"], label=f"R = {refl}")[0]
        ax.plot(z * 100, s, "o", color=line.get_color())
        ax.plot(zz * 100, np.sqrt(f["c0"] + f["c1"] * 0.5 * sf), ":", color=line.get_color())
    for ax, title in zip(axes, ("no fog", "3 µm fog")):
        ax.set_yscale("log")
        ax.set_xlabel("distance (cm)")
        ax.set_title(f"{title}: patch signal (fit, dots) and noise (dotted)")
        ax.legend()
    axes[0].set_ylabel("e⁻ per reading")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def _plot_contrast(beta: float | None, path: Path) -> None:
    """Figure 6 (:func:`contrast_figure`) written to ``path`` as a PNG."""
    import matplotlib.pyplot as plt  # start-up: loads matplotlib, PIL, cycler (298 ms here)

    fig = contrast_figure(beta)
    fig.savefig(path, dpi=100, bbox_inches="tight", pad_inches=0.1)
    plt.close(fig)


def contrast_figure(beta: float | None) -> Any:
    """Figure 6: Koschmieder contrast ``C/C₀ = e^{−βz}`` (Eq. 8) vs distance, with the visibility
    ``−ln(0.05)/β`` (Eq. 9), for the chamber's β and for β with Table 1's Q_ext = 0.8; the
    matplotlib figure (the caller closes it)."""
    import matplotlib  # start-up: loads matplotlib, PIL, cycler (78 ms here)

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # start-up: loads matplotlib, PIL, cycler (298 ms here)

    if beta is None:
        beta = MieFog().extinction_per_m
    q = MieFog().mie.q_ext
    betas = {
        f"chamber, Mie Q_ext = {q:.2f}: β = {beta:.2f} /m": beta,
        f"Table 1's Q_ext = 0.8: β = {beta * 0.8 / q:.2f} /m": beta * 0.8 / q,
    }
    fig, ax = plt.subplots(figsize=(6, 4))
    zmax = 1.2 * visibility_m(min(betas.values()))
    z = np.linspace(0.0, zmax, 400)
    for label, b in betas.items():
        line = ax.plot(z, koschmieder_contrast(1.0, b, z), label=label)[0]
        v = visibility_m(b)
        ax.axvline(v, color=line.get_color(), ls=":")
        # across the top beside its line, away from the middle of the plot: along its line at mid
        # height the chamber's label crossed the other curve (issue 43)
        right = v < 0.5 * zmax
        ax.annotate(
            f"visibility {v:.2f} m",
            (v, 0.92),
            xytext=(4 if right else -4, 0),
            textcoords="offset points",
            color=line.get_color(),
            ha="left" if right else "right",
            va="center",
        )
    ax.axhline(0.05, color="gray", lw=0.8, label="5 % contrast: the visibility's threshold")
    ax.set_xlabel("distance z (m)")
    ax.set_ylabel("contrast C / C₀")
    ax.set_title("Figure 6: contrast vs distance in fog (Eq. 8)")
    # below the axes: inside, it lay over the visibility lines (issue 34: legends never cover data)
    ax.legend(fontsize=8, loc="upper center", bbox_to_anchor=(0.5, -0.16), ncol=1, frameon=False)
    return fig
