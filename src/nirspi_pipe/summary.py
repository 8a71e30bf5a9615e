"""The one-run summary printed by ``nirspi-run`` (and ``RunResult.summary()``): which physical
effects were on, each metric with a one-line explanation, and the time of every stage.

Works on a run record (the dict written to ``record.json``, see :mod:`nirspi_pipe.records`), so
the same text comes from the command line, the Python API and an old record read back.
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping
from pathlib import Path
from typing import Any

__all__ = ["METRIC_HELP", "degenerate_reasons", "effects_lines", "format_summary", "metric_lines"]

#: The ``ms:`` line shows the stage build (``timings_ms.build``, not in ``total``) from this many ms
#: (assumed: 10 s, three times the slowest warm build measured, 3.4 s for the README's 3D example
#: at load 7.5 on 2 cores, and a ninth of the 90 s that compiling the mesh kernels on a cold numba
#: cache took in that run's first try, load ~4).
BUILD_SHOWN_MS = 10_000.0

#: Metric name -> (format of the value, one-line explanation). The order is the display order.
METRIC_HELP: dict[str, tuple[str, str]] = {
    "ssim": ("{:.3f}", "structural similarity to the true radiance: 1 = identical, 0 = no shared structure"),
    "psnr": ("{:.2f} dB", "peak signal-to-noise ratio, peak = a white target; +6 dB = half the error"),
    "rmse": ("{:.4g}", "root-mean-square radiance error, Eq. (16), raw (no gain/offset fit), white target = 1"),
    "upscale_psnr": ("{:.2f} dB", "PSNR of the upscaled image against the scene rendered at its resolution"),
    "upscale_gain_db": ("{:+.2f} dB", "the upscaler's PSNR minus bicubic's on the same reconstruction"),
    "depth_rmse_sfs_offsetfree_mm": (
        "{:.3g} mm",
        "depth error of shape from shading alone (Alg. A2) with its best constant offset, Eq. (16)",
    ),
    "depth_rmse_fused_mm": ("{:.3g} mm", "depth error after fusing SFS with the four iToF points (Alg. A3)"),
    "improvement_offsetfree_pct": (
        "{:+.1f} %",
        "Eq. (17): how much fusion cut that SFS depth error; negative = the fused depth is worse than SFS",
    ),
    "skewness_mean": ("{:.3f}", "mean equiangle skewness of the mesh's triangles: 0 = equilateral, 1 = degenerate"),
    "chamfer_mm": ("{:.3g} mm", "mean distance between the final mesh and the true surface"),
    "hausdorff_mm": ("{:.3g} mm", "largest distance between the final mesh and the true surface"),
}

_LABELS = {
    "ssim": "SSIM",
    "psnr": "PSNR",
    "rmse": "RMSE",
    "upscale_psnr": "upscaled PSNR",
    "upscale_gain_db": "gain over bicubic",
    "depth_rmse_sfs_offsetfree_mm": "depth RMSE, SFS",
    "depth_rmse_fused_mm": "depth RMSE, fused",
    "improvement_offsetfree_pct": "improvement",
    "skewness_mean": "skewness",
    "chamfer_mm": "chamfer",
    "hausdorff_mm": "Hausdorff",
}


def _num(x: Any) -> float:
    try:
        return float(x)
    except (TypeError, ValueError):
        return math.nan


def _time_varying(node: Mapping[str, Any], keys: tuple[tuple[str, str], ...]) -> str:
    parts = [f"{label} {100 * _num(node.get(k)):.0f} %" for k, label in keys if _num(node.get(k)) > 0]
    return f" + {', '.join(parts)}" if parts else ""


def _fog_line(choices: Mapping[str, Any], fog: Mapping[str, Any], derived: Mapping[str, Any]) -> str:
    """The fog's line: off, or its extinction, visibility, round-trip transmittance and fluctuation."""
    beta = _num(derived.get("beta_per_m", 0.0))
    if choices.get("fog") in (None, "none") or not beta > 0:
        return "fog        off (fog=none): clear air"
    vis = _num(derived.get("visibility_m"))
    vis_s = f", visibility {vis:.2f} m (Koschmieder, 5 % contrast)" if math.isfinite(vis) else ""
    tr = _num(derived.get("transmittance_roundtrip"))
    tr_s = f", {100 * tr:.0f} % of the light survives the round trip" if math.isfinite(tr) else ""
    tv = _time_varying(fog, (("fluctuation_rel", "density fluctuation"),))
    return f"fog        {choices.get('fog')}: extinction β = {beta:.3g} /m{vis_s}{tr_s}{tv}"


def _background_line(choices: Mapping[str, Any], light: Mapping[str, Any], derived: Mapping[str, Any]) -> str:
    """The background light's line: off, or its illuminance, irradiance in the band and variation."""
    klux = _num(derived.get("klux", light.get("klux", 0.0)))
    if choices.get("illumination") in (None, "none") or not klux > 0:
        return "background off (illumination=none): dark room"
    irr = _num(derived.get("background_irradiance_w_m2"))
    band = light.get("band_nm") or []
    band_s = f" in the {band[0]:g}–{band[1]:g} nm band" if len(band) == 2 else ""
    irr_s = f" = {irr:.3g} W/m²{band_s}" if math.isfinite(irr) else ""
    tv = _time_varying(
        light, (("flicker_rel", "flicker"), ("wander_rel", "wander"), ("drift_rel_per_s", "drift per s"))
    )
    return f"background {klux:g} kLux{irr_s}{tv}"


def _detector_line(choices: Mapping[str, Any], derived: Mapping[str, Any]) -> str:
    """The detector's line: ideal, or its SNR per reading and count of saturated patterns."""
    det = choices.get("detector")
    snr = _num(derived.get("snr_db"))
    sat = int(_num(derived.get("saturated_patterns", 0)) or 0)
    if det in (None, "ideal"):
        return "detector   ideal (detector=ideal): no photon, dark or read noise, no ADC"
    snr_s = f": SNR {snr:.1f} dB per reading" if math.isfinite(snr) else ""
    return f"detector   {det}{snr_s}, {sat} saturated pattern{'s' if sat != 1 else ''}"


def effects_lines(record: Mapping[str, Any]) -> list[str]:
    """One line per physical effect group (fog, background light, detector, extra noise): on
    with its size, or off. Empty for sources that replay measurements (nothing is simulated)."""
    choices = record.get("choices", {}) or {}
    config = record.get("config", {}) or {}
    derived = record.get("derived", {}) or {}
    if choices.get("source", "simulator") != "simulator":
        return [f"source     {choices.get('source')}: measured data, no simulated effects"]
    lines = [
        _fog_line(choices, config.get("fog") or {}, derived),
        _background_line(choices, config.get("illumination") or {}, derived),
        _detector_line(choices, derived),
    ]
    mux = _multiplex_line(record)
    if mux:
        lines.append(mux)
    noise = _num((config.get("source") or {}).get("noise_rel", 0.0))
    if noise > 0:
        lines.append(f"noise      extra Gaussian noise {noise:g} of the mean reading (source.noise_rel)")
    return lines


def _multiplex_line(record: Mapping[str, Any]) -> str | None:
    """The per-pixel SNR that the reading SNR leaves after the exact inverse of M split
    Hadamard patterns, or None without a reading SNR. A reading of the lit half of N pixels
    carries ``S = (N/2)·x̄`` with noise σ; the ±1 difference of a pair has noise √2·σ, and the
    inverse ``x = Hᵀd/N`` sums M of them into each pixel: noise ``√(2M)·σ/N``, so the mean pixel's
    SNR is ``SNR_reading·√(2/M)``, i.e. ``SNR_reading + 10·log10(2/M)`` dB: 15.1 dB below the
    reading at 8² (M = 64), 33.1 dB below at 64² (M = 4096). Measured as the mean pixel over the
    spread of the object-free pixels: ``nirspi-run preset=null`` (64²) predicted −3.1 dB, measured
    −3.4 dB (tests/test_summary_notes.py); the default 8² run 14.9 dB against 11.7 dB over its
    40 object-free pixels (the daylight wander and fog fluctuation add to the noise)."""
    derived = record.get("derived", {}) or {}
    snr = _num(derived.get("snr_db"))
    m = _num(((record.get("info", {}) or {}).get("source") or {}).get("patterns_measured"))
    if not (math.isfinite(snr) and m >= 1) or abs(snr) >= 200:  # 200 dB: the noise-free clip
        return None
    pixel = snr + 10.0 * math.log10(2.0 / m)
    solver = (record.get("choices", {}) or {}).get("solver")
    exact = "" if solver in ("fwht", "lstsq", "correlation") else f" (solver={solver} may denoise)"
    low = "; the noise rivals the image: hence the low SSIM/PSNR" if pixel < 6 else ""
    return (
        f"multiplex  {m:.0f} patterns share each reading's noise: the mean pixel's SNR after the inverse ≈ "
        f"{snr:.1f} dB + 10·log10(2/{m:.0f}) = {pixel:.1f} dB{exact}{low}"
    )


#: Depth baselines other than the headline's (offset-free): metric keys and their words.
_OTHER_BASELINES = (
    ("depth_rmse_sfs_mm", "improvement_pct", "median placed at the working distance"),
    ("depth_rmse_sfs_fit_mm", "improvement_fit_pct", "the fusion's iToF global fit"),
)


#: Normalised scores that :func:`nirspi_pipe.metrics.content_test` may leave out: metric-key
#: prefix -> the label of its line.
_SCORED = {"": "SSIM, PSNR", "upscale_": "upscaled PSNR"}
_LEFT_OUT = re.compile(
    r"metrics: (?P<why>.*), so the normalised (?P<prefix>\w*?)psnr/\w*ssim are undefined and left out"
)


def degenerate_reasons(warnings: list[str] | tuple[str, ...]) -> dict[str, str]:
    """Metric-key prefix -> why its normalised PSNR/SSIM were left out, read from the record's
    warnings (the metrics stage writes one per prefix)."""
    out: dict[str, str] = {}
    for w in warnings:
        m = _LEFT_OUT.search(str(w))
        if m:
            out.setdefault(m.group("prefix"), m.group("why"))
    return out


def _degenerate_line(metrics: Mapping[str, float], prefix: str, reasons: Mapping[str, str]) -> str | None:
    """One line saying that the normalised scores of ``prefix`` are degenerate, and why; None
    where they are not (or the run has no such scores)."""
    flags = [f for f in ("degenerate_reference", "degenerate_image") if f"{prefix}{f}" in metrics]
    if not flags:
        return None
    why = reasons.get(prefix)
    if why is None:  # an old record, or one read without its warnings: what the flags say
        t = _num(metrics.get(f"{prefix}content_t"))
        why = (
            "the reference is uniform, dark or not finite"
            if flags[0] == "degenerate_reference"
            else f"no detectable trace of the reference (fitted gain's t = {t:.2f}, below 5σ)"
            if math.isfinite(t)
            else "the image is constant, or computed from a camera image without content"
        )
    return f"{_SCORED[prefix]:<18} {'degenerate':>10}  left out ({prefix}{flags[0]}=1): {why}"


def _rmse_note(metrics: Mapping[str, float]) -> str:
    """The note under the RMSE: which SSIM/PSNR the lines show, and the raw ones, as the RMSE."""
    raw = f"PSNR {_num(metrics['psnr_raw']):.2f} dB" + (
        f", SSIM {_num(metrics['ssim_raw']):.3f}" if "ssim_raw" in metrics else ""
    )
    fitted = (
        "SSIM/PSNR above: after a least-squares gain and offset to the camera's noise-free image"
        if "psnr" in metrics
        else "no fitted SSIM/PSNR: the reference is uniform, dark or not finite (degenerate_reference)"
        if "degenerate_reference" in metrics
        else "no fitted SSIM/PSNR: degenerate, see above"
    )
    return f"{'':<18} {'':>10}  ({fitted}; raw, as the RMSE: {raw})"


def _baselines_note(metrics: Mapping[str, float]) -> str | None:
    """The note under the offset-free improvement: the other SFS baselines, or None without them."""
    others = [
        f"{words} {_num(metrics[rm]):.3g} mm ({_num(metrics[ip]):+.1f} %)"
        for rm, ip, words in _OTHER_BASELINES
        if rm in metrics and ip in metrics
    ]
    if not others:
        return None
    return f"{'':<18} {'':>10}  (other SFS baselines: {'; '.join(others)}; docs/paper.md, Table 3)"


def _metric_line(metrics: Mapping[str, float], k: str) -> list[str]:
    """The line of metric ``k`` (``label  value  explanation``) and the note that follows it, if any."""
    fmt, text = METRIC_HELP[k]
    v = _num(metrics[k])
    value = fmt.format(v) if math.isfinite(v) else str(v)
    lines = [f"{_LABELS[k]:<18} {value:>10}  {text}"]
    if k == "rmse" and "psnr_raw" in metrics:
        lines.append(_rmse_note(metrics))
    if k == "improvement_offsetfree_pct":
        note = _baselines_note(metrics)
        if note:
            lines.append(note)
    return lines


def metric_lines(metrics: Mapping[str, float], warnings: list[str] | tuple[str, ...] = ()) -> list[str]:
    """The explained metrics, one per line (``label  value  explanation``), notes where two lines
    use different conventions (fitted PSNR/SSIM against the raw RMSE; the other SFS baselines
    of Eq. 17), then a count of the others (in ``record.json``). A normalised score left out as
    degenerate (:func:`nirspi_pipe.metrics.content_test`) is one line ``degenerate`` with its
    reason (from ``warnings``, the record's, when given)."""
    reasons = degenerate_reasons(warnings)
    shown = [k for k in METRIC_HELP if k in metrics]
    lines = []
    degenerate = {p: _degenerate_line(metrics, p, reasons) for p in _SCORED}
    if degenerate[""]:
        lines.append(degenerate[""])
    for k in shown:
        lines += _metric_line(metrics, k)
    if degenerate["upscale_"]:
        at = next((i for i, s in enumerate(lines) if s.startswith(_LABELS["upscale_gain_db"])), len(lines))
        lines.insert(at, degenerate["upscale_"])
    rest = len(metrics) - len(shown)
    if rest > 0:
        lines.append(f"(+{rest} more metrics in record.json)")
    return lines


def _sampled(record: Mapping[str, Any], res: Any) -> str:
    """The head's note on a partial scan: the patterns measured of all, or the ratio asked."""
    ratio = _num((((record.get("config", {}) or {}).get("scan")) or {}).get("ratio", 1.0))
    if not (math.isfinite(ratio) and ratio < 1):
        return ""
    # what was measured, not 100 * ratio (1e-300 measured 1 pattern)
    measured = ((record.get("info") or {}).get("source") or {}).get("patterns_measured")
    if isinstance(measured, int) and not isinstance(measured, bool) and isinstance(res, int) and res > 0:
        return f", {measured} of {res * res} patterns ({100 * measured / (res * res):.3g} %)"
    return f", scan.ratio={ratio:.3g}"


def _timings_line(t: Mapping[str, Any]) -> str:
    """The stage times in ms, the total, and the build time when it is large enough to show."""
    stages = " | ".join(f"{k} {v:.1f}" for k, v in t.items() if k not in ("build", "total"))
    line = f"  ms: {stages} | total {t.get('total', 0.0):.1f}"
    build = t.get("build")
    if isinstance(build, (int, float)) and build >= BUILD_SHOWN_MS:  # compiling kernels: not hidden
        line += f" | build {build:.1f} before the stages, not in total (a first run compiles their kernels)"
    return line


def _out_line(out_dir: Path, warned: list[str]) -> str:
    """The run's folder, and its summary picture where this run wrote one."""
    unwritten = any(w.startswith("summary.png not written") for w in warned)  # an older file may be there
    pic = (
        "  (summary.png: truth, reconstruction, error)"
        if (Path(out_dir) / "summary.png").exists() and not unwritten
        else ""
    )
    return f"  -> {out_dir}{pic}"


def format_summary(record: Mapping[str, Any], out_dir: Path | None = None) -> str:
    """The multi-line summary of one run record (see the module docstring)."""
    choices = record.get("choices", {}) or {}
    cfg = record.get("config", {}) or {}
    meta = record.get("meta", {}) or {}
    res = (cfg.get("camera") or {}).get("resolution")
    head = (
        f"nirspi-run: scene={choices.get('scene')} scan={choices.get('scan')} "
        f"solver={choices.get('solver')} {res}x{res}{_sampled(record, res)} seed={meta.get('seed')}"
    )
    lines = [head]
    if meta.get("status", "ok") != "ok":
        lines.append(f"  FAILED: {meta.get('error')}")
    lines += ["  " + s for s in effects_lines(record)]
    warned = [str(w) for w in meta.get("warnings", []) or []]
    lines += ["  " + s for s in metric_lines(record.get("metrics", {}) or {}, warned)]
    t = record.get("timings_ms", {}) or {}
    if t:
        lines.append(_timings_line(t))
    lines += [f"  warning: {w}" for w in warned if not _LEFT_OUT.search(w)]  # those shown on the metric's own line
    if out_dir is not None:
        lines.append(_out_line(out_dir, warned))
    return "\n".join(lines)
