"""Regenerate the numbers the README quotes, from runs made now, as one Markdown fragment.

    python -m nirspi_pipe.readme_numbers                 # a few minutes on 2 cores
    python -m nirspi_pipe.readme_numbers --install       # + size and time of `pip install .`
    python -m nirspi_pipe.readme_numbers --paper         # + the full paper sweep (minutes more)

Writes ``docs/readme_numbers.md`` (``--out``): the machine (platform, CPU, cores) and its load
average before and after, the git commit, then

* the default run (``nirspi-run`` with no arguments): its effects and metrics;
* the README's sweep example (``-m illumination.klux=5,15,50 seed=0,1,2``): PSNR/SSIM per kLux,
  mean ± std over the seeds;
* wall times of the README's sweeps (``table2``, ``paper_ci``; ``paper`` with ``--paper``), each
  also as a ratio to one reference run timed in the same session (the default run in a fresh
  process), because on a shared machine the seconds vary with the load and the ratios less;
* with ``--install``: the size of a fresh venv after ``pip install <repo>`` and the time it took.

Every sweep runs in a temporary folder with the installed ``nirspi-run``; nothing else is written.

It runs from a clone of the repository (the README and docs it writes for, the source ``--install``
installs): the clone holding this module (an editable install) or else the working directory or
one of its parents. Anywhere else (e.g. after a plain ``pip install .``) it refuses with one line
and exit status 2.
"""

from __future__ import annotations

import argparse
import datetime as dt
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from nirspi_pipe.app.api import load_results

__all__ = ["find_clone", "machine_stamp", "main", "timed"]

_PROG = "python -m nirspi_pipe.readme_numbers"
_HERE = Path(__file__).resolve()


def _is_clone(folder: Path) -> bool:
    """A checkout of this project: a git work tree whose pyproject.toml names nirspi-pipe."""
    try:
        text = (folder / "pyproject.toml").read_text()
    except OSError:
        return False
    return (folder / ".git").exists() and 'name = "nirspi-pipe"' in text


def find_clone(cwd: Path | None = None) -> Path | None:
    """The clone to measure and write into: the one holding this module (an editable install,
    ``src/nirspi_pipe/``), else ``cwd`` (default: the working directory) or one of its parents;
    None when none is a clone (an installed package run from elsewhere)."""
    start = (cwd or Path.cwd()).resolve()
    for folder in (_HERE.parents[2], start, *start.parents):
        if _is_clone(folder):
            return folder
    return None


def _cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown CPU"


def _load() -> str:
    try:
        return " / ".join(f"{x:.1f}" for x in os.getloadavg())
    except OSError:
        return "unknown"


def machine_stamp(repo: Path | None = None) -> dict[str, str]:
    """Platform, CPU, cores, load average (1/5/15 min), UTC time, git commit of ``repo`` (default:
    :func:`find_clone`'s)."""
    sha = "unknown"
    repo = repo or find_clone()
    try:
        if repo is None:
            raise OSError("not in a clone")
        sha = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], cwd=repo, capture_output=True, text=True, timeout=5, check=True
        ).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        pass
    return {
        "when": dt.datetime.now(dt.timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
        "platform": f"{platform.system()} {platform.machine()}, Python {platform.python_version()}",
        "cpu": f"{_cpu_model()}, {os.cpu_count()} cores",
        "load": _load(),
        "commit": sha,
    }


def _exe(name: str) -> str:
    cand = Path(sys.executable).with_name(name)
    return str(cand) if cand.exists() else (shutil.which(name) or name)


def timed(args: list[str], cwd: Path, timeout: float = 3600.0) -> float:
    """Wall seconds of one command (raises with its stderr when it fails)."""
    env = dict(os.environ, MPLBACKEND="Agg")
    env.setdefault("OPENBLAS_NUM_THREADS", "1")
    t0 = time.perf_counter()
    res = subprocess.run(args, cwd=cwd, capture_output=True, text=True, timeout=timeout, env=env, check=False)
    wall = time.perf_counter() - t0
    if res.returncode != 0:
        raise RuntimeError(f"{' '.join(args)} failed ({res.returncode}): {res.stderr.strip()[-500:]}")
    return wall


def _default_run(tmp: Path) -> tuple[str, float]:
    """The default run in a fresh process (the reference time) and its printed summary."""
    env = dict(os.environ, MPLBACKEND="Agg")
    env.setdefault("OPENBLAS_NUM_THREADS", "1")
    t0 = time.perf_counter()
    res = subprocess.run(
        [_exe("nirspi-run"), "hydra.run.dir=default"],
        cwd=tmp,
        capture_output=True,
        text=True,
        timeout=600,
        env=env,
        check=True,
    )
    text = res.stdout.strip().replace(str(tmp / "default"), "outputs/<date>/<time>")
    return text, time.perf_counter() - t0


def _sweep_table(tmp: Path) -> tuple[str, float]:
    import pandas as pd  # start-up: loads pandas, pyarrow, cloudpickle (312 ms here)

    wall = timed(
        [_exe("nirspi-run"), "-m", "illumination.klux=5,15,50", "seed=0,1,2", "hydra.sweep.dir=sweeps/klux"], tmp
    )
    df = load_results(tmp / "sweeps" / "klux")
    ok = df[df["status"] == "ok"]
    g = ok.groupby("illumination.klux")[["metrics.psnr", "metrics.ssim"]].agg(["mean", "std"])
    rows = ["| kLux | PSNR (dB), mean ± std | SSIM, mean ± std |", "|---:|---:|---:|"]
    for klux, r in g.iterrows():
        rows.append(
            f"| {float(klux):g} | {r[('metrics.psnr', 'mean')]:.2f} ± {r[('metrics.psnr', 'std')]:.2f} "
            f"| {r[('metrics.ssim', 'mean')]:.3f} ± {r[('metrics.ssim', 'std')]:.3f} |"
        )
    rows.append(f"\n{len(ok)} of {len(df)} jobs ok; {pd.Timestamp.now(tz='UTC'):%H:%M} UTC.")
    return "\n".join(rows), wall


def _mesh_stage_ms(sweep: Path) -> str:
    """Table 6's 3D mesh stage (fusion + surface, ms) over the 3D jobs of a sweep: median and range."""
    df = load_results(sweep)
    cols = ("timings_ms.fusion", "timings_ms.surface")
    if not all(c in df for c in cols):
        return "no 3D jobs"
    t = (df[cols[0]] + df[cols[1]]).dropna()
    if t.empty:
        return "no 3D jobs"
    return f"{t.median():.0f} ms median, {t.min():.0f}–{t.max():.0f} ms over {len(t)} jobs"


def _install(tmp: Path, repo: Path) -> tuple[float, float]:
    """(seconds, MB) of ``pip install <repo>`` into a fresh venv (pip's cache as configured)."""
    venv = tmp / "venv"
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True, timeout=300)
    wall = timed([str(venv / "bin" / "pip"), "install", "-q", str(repo)], tmp)
    total = sum(f.stat().st_size for f in venv.rglob("*") if f.is_file() and not f.is_symlink())
    return wall, total / 1e6


def main(argv: list[str] | None = None) -> None:
    """Command line: see the module docstring."""
    ap = argparse.ArgumentParser(prog=_PROG, description=__doc__.split("\n")[0])
    ap.add_argument(
        "--out", type=Path, default=None, help="Markdown fragment to write (default: docs/readme_numbers.md)"
    )
    ap.add_argument("--paper", action="store_true", help="also time the full paper sweep (+experiment=paper)")
    ap.add_argument("--install", action="store_true", help="also measure pip install . in a fresh venv")
    ns = ap.parse_args(argv)
    repo = find_clone()
    if repo is None:
        print(
            f"{_PROG}: error: not run from a clone of nirspi-pipe (the installed package is at {_HERE.parent} "
            f"and {Path.cwd()} is not in a clone): cd into a git clone of the repository and run it there",
            file=sys.stderr,
        )
        raise SystemExit(2)
    ns.out = ns.out or repo / "docs" / "readme_numbers.md"

    before = machine_stamp(repo)
    out: list[str] = []
    with tempfile.TemporaryDirectory(prefix="nirspi-readme-") as t:
        tmp = Path(t)
        summary, ref_s = _default_run(tmp)
        table, klux_s = _sweep_table(tmp)
        sweeps = [("the README's sweep example, 9 jobs", "-m illumination.klux=5,15,50 seed=0,1,2", klux_s)]
        mesh_ms = {}
        for name, jobs in (("table2", 48), ("paper_ci", 44)) + ((("paper", 2608),) if ns.paper else ()):
            wall = timed([_exe("nirspi-run"), "-m", f"+experiment={name}", f"hydra.sweep.dir=sweeps/{name}"], tmp)
            sweeps.append((f"{jobs} jobs", f"-m +experiment={name}", wall))
            if name != "table2":
                mesh_ms[name] = _mesh_stage_ms(tmp / "sweeps" / name)
        install = _install(tmp, repo) if ns.install else None
    after = machine_stamp(repo)

    out += [
        "<!-- generated by `python -m nirspi_pipe.readme_numbers`; do not edit by hand -->",
        "### Numbers of this README, regenerated",
        "",
        (
            f"`python -m nirspi_pipe.readme_numbers{' --install' if ns.install else ''}"
            f"{' --paper' if ns.paper else ''}`, {before['when']}, commit {before['commit']}: {before['platform']}; "
            f"{before['cpu']}; load average (1/5/15 min) {before['load']} before, {after['load']} after."
        ),
        "",
        "The default run (`nirspi-run`, no arguments):",
        "",
        "```text",
        summary,
        "```",
        "",
        "The README's sweep example, `nirspi-run -m illumination.klux=5,15,50 seed=0,1,2`:",
        "",
        table,
        "",
        (
            f"Wall times, and as a ratio to the default run in a fresh process ({ref_s:.1f} s here, the "
            "reference: on a loaded machine both grow, the ratio less):"
        ),
        "",
        "| command | wall time | × default run |",
        "|---|---:|---:|",
        f"| `nirspi-run` (default run, reference) | {ref_s:.1f} s | 1 |",
    ]
    for label, _args, wall in sweeps:
        out.append(f"| `nirspi-run {_args}` ({label}) | {wall:.1f} s | {wall / ref_s:.1f} |")
    for name, text in mesh_ms.items():
        out.append(
            f"\nTable 6's 3D mesh stage (fusion + power crust) in `+experiment={name}`, jobs two at a time "
            f"on this machine: {text}."
        )
    if install is not None:
        out += [
            "",
            (
                f"`pip install .` into a fresh venv: {install[0]:.0f} s, {install[1]:.0f} MB on disk "
                "(pip's wheel cache as configured on this machine)."
            ),
        ]
    ns.out.parent.mkdir(parents=True, exist_ok=True)
    ns.out.write_text("\n".join(out) + "\n")
    print("\n".join(out))
    print(f"-> {ns.out}", file=sys.stderr)


if __name__ == "__main__":
    main()
