"""``nirspi-bench gpu``: one GPU check — parity on the GPU, then OMP, SFS, FSRCNN and the 3D path,
GPU against CPU in the same run, one summary (``summary.md`` and ``summary.json``).

Needs a machine with Python and the project installed (``pip install '.[train]'`` for the torch
parts); nothing else. On a machine without a GPU the CPU parts run and every GPU part prints one
``SKIPPED (no GPU): ...`` line, so the script itself is tested where CI runs.

Steps, each in a child process under its own time limit (a driver that hangs costs one step),
all within ``--budget`` seconds (default 330, under the 6 minutes of a GPU loan):

1. ``opencl``: the OpenCL devices. Where no ICD names NVIDIA's library, the first
   ``libnvidia-opencl.so.1`` found (driver folders, ``ldconfig``) is given to the ICD loader
   through ``OCL_ICD_VENDORS`` (a folder with a single ``nvidia.icd``), as
   shared/gpu-reference/run.sh did by hand. The GPU is then named to every later step by
   ``PYOPENCL_CTX`` (``platform:device``), which ``device: auto`` honours.
2. ``parity``: ``pytest`` on the OpenCL and torch parity tests with the GPU as the device (a
   source checkout only: the tests are not in the wheel).
3. ``omp``: numpy against OpenCL on the GPU (and on the CPU device, where there is one) at 64²
   (256 atoms) and 128² (1000 atoms), images compared (target ≤ 1e-10), and a batch of 32
   problems of 32² in one device solve against 32 numpy solves.
4. ``sfs``: godunov, lax_friedrichs and second_order at 64², 128², 256², numpy against OpenCL on
   the GPU (work-group: the device's choice, and 64, 256, 1024 work-items at 256²).
5. ``fsrcnn``: 64² → 256² (×4): numpy, torch on the CPU, torch on CUDA with TF32 off and on.
6. ``mesh3d``: ``nirspi-bench mesh3d`` at 64² with second-order SFS on numpy and on OpenCL.

``--write-table`` writes, per device, stage and size, which back end was faster into the table
that ``backend: auto`` reads (:mod:`nirspi_pipe.opencl_devices`).
"""

from __future__ import annotations

import argparse
import atexit
import contextlib
import glob
import io
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from nirspi_pipe.benchmarks import mesh3d
from nirspi_pipe.opencl_devices import write_table
from nirspi_pipe.patterns.orders import Zigzag
from nirspi_pipe.scene.objects import ImageTarget
from nirspi_pipe.solvers.omp_opencl import opencl_context
from nirspi_pipe.strictjson import dumps_strict
from nirspi_pipe.types import Camera

SKIP_NO_GPU = "SKIPPED (no GPU): "


def best_ms(fn: Any, repeat: int) -> float:
    """Best of ``repeat`` timed calls after one warm-up, ms."""
    fn()
    out = float("inf")
    for _ in range(max(1, repeat)):
        t = time.perf_counter()
        fn()
        out = min(out, time.perf_counter() - t)
    return out * 1e3


# --- the parts (each runs in a child: python -m nirspi_pipe.benchmarks.gpu --part NAME) ---------


def _save(ns: argparse.Namespace, part: str, result: dict[str, Any]) -> None:
    """Write a part's result so far (a step cut by its time limit keeps the rows it finished)."""
    (Path(ns.out) / f"{part}.json").write_text(dumps_strict(result, indent=1))


def _opencl_devices() -> list[dict[str, Any]]:
    import pyopencl as cl  # start-up: loads pyopencl, attrs, pytools (62 ms here)

    out = []
    for pi, p in enumerate(cl.get_platforms()):
        for di, d in enumerate(p.get_devices()):
            out.append(
                {
                    "spec": f"{pi}:{di}",
                    "name": d.name.strip(),
                    "platform": p.name.strip(),
                    "gpu": bool(d.type & cl.device_type.GPU),
                    "fp64": "cl_khr_fp64" in d.extensions,
                }
            )
    return out


def part_opencl(_: argparse.Namespace) -> dict[str, Any]:
    try:
        devs = _opencl_devices()
    except Exception as exc:  # noqa: BLE001 - report it
        return {"devices": [], "error": f"{type(exc).__name__}: {exc}"}
    for d in devs:
        print(f"  {d['spec']}  {d['platform']} / {d['name']}  gpu={d['gpu']} fp64={d['fp64']}")
    return {"devices": devs}


def part_omp(ns: argparse.Namespace) -> dict[str, Any]:
    # start-up: loads scipy, charset_normalizer (230 ms here)
    from nirspi_pipe.solvers.omp import (
        omp_hadamard,
        omp_hadamard_batch,
    )
    from nirspi_pipe.sources.simulator import Simulator  # start-up: loads 24 modules of ours (39 ms here)

    rows = []
    for n, atoms in ((64, 256), (128, 1000)):
        scene = ImageTarget().render(Camera(resolution=n))
        acq = Simulator().acquire(scene, Zigzag(0.25).select(n), n, np.random.default_rng(0))
        y = acq.coefficients()
        ref, _ = omp_hadamard(y, n, acq.indices, max_atoms=atoms, backend="numpy")
        row: dict[str, Any] = {"size": n, "atoms": atoms}
        row["numpy_ms"] = best_ms(lambda: omp_hadamard(y, n, acq.indices, max_atoms=atoms), ns.repeat)
        for label, spec in (("gpu", ns.gpu), ("cpu_device", ns.cpu)):
            if spec is None or (label == "cpu_device" and n > 64):  # PoCL: 128² takes ~15 s
                continue
            opencl_context(spec)
            img, _ = omp_hadamard(y, n, acq.indices, max_atoms=atoms, backend="opencl", device=spec)
            row[f"{label}_ms"] = best_ms(
                lambda: omp_hadamard(y, n, acq.indices, max_atoms=atoms, backend="opencl", device=spec),
                ns.repeat if label == "gpu" else 1,
            )
            row[f"{label}_max_diff"] = float(np.max(np.abs(img - ref)))
            if label == "gpu":  # both layouts of the device solve (the default is one of them)
                for mode in ("kernels", "workgroup"):
                    img, _ = omp_hadamard(
                        y, n, acq.indices, max_atoms=atoms, backend="opencl", device=spec, opencl_mode=mode
                    )
                    row[f"gpu_{mode}_ms"] = best_ms(
                        lambda: omp_hadamard(
                            y, n, acq.indices, max_atoms=atoms, backend="opencl", device=spec, opencl_mode=mode
                        ),
                        ns.repeat,
                    )
                    row[f"gpu_{mode}_max_diff"] = float(np.max(np.abs(img - ref)))
        rows.append(row)
        print("  " + json.dumps(row))
        _save(ns, "omp", {"rows": rows})
    batch: dict[str, Any] = {}
    if ns.gpu is not None:  # 32 problems of 32² at 25 %, same patterns: one device solve vs 32 numpy ones
        n, nb = 32, 32
        idx = Zigzag(0.25).select(n)
        ys = np.random.default_rng(3).standard_normal((nb, len(idx)))
        refs = [omp_hadamard(y, n, idx, max_atoms=64)[0] for y in ys]
        imgs, _ = omp_hadamard_batch(ys, n, idx, max_atoms=64, device=ns.gpu)
        batch = {
            "problems": nb,
            "size": n,
            "numpy_ms": best_ms(lambda: [omp_hadamard(y, n, idx, max_atoms=64) for y in ys], 1),
            "gpu_batch_ms": best_ms(lambda: omp_hadamard_batch(ys, n, idx, max_atoms=64, device=ns.gpu), ns.repeat),
            "max_diff": float(max(np.max(np.abs(a - b)) for a, b in zip(imgs, refs))),
        }
        print("  batch " + json.dumps(batch))
    else:
        print("  " + SKIP_NO_GPU + "OMP on the GPU and the batched solve")
    return {"rows": rows, "batch": batch}


def part_sfs(ns: argparse.Namespace) -> dict[str, Any]:
    from nirspi_pipe.benchmarks.sfs import sphere_problem  # start-up: loads 7 modules of ours (30 ms here)

    # start-up: loads 6 modules of ours (24 ms here)
    from nirspi_pipe.sfs.opencl import (
        default_local_size,
        solve_opencl,
    )

    # start-up: loads 5 modules of ours (23 ms here)
    from nirspi_pipe.sfs.sweeping import (
        BIG,
        SweepProblem,
        solve_numpy,
    )

    rows = []
    for n in ns.sfs_sizes:
        f, fixed, z_true, _, _, _ = sphere_problem(n)
        problem = SweepProblem(f, fixed, np.where(fixed, z_true, BIG))
        for scheme in ("godunov", "lax_friedrichs", "second_order"):
            slow = scheme == "lax_friedrichs"
            ref = solve_numpy(problem, scheme, 1e-4, 8000)
            row: dict[str, Any] = {"size": n, "scheme": scheme, "sweeps": ref.sweeps}
            row["numpy_ms"] = best_ms(lambda: solve_numpy(problem, scheme, 1e-4, 8000), 0 if slow else ns.repeat)
            for label, spec in (("gpu", ns.gpu), ("cpu_device", ns.cpu)):
                if spec is None:
                    continue
                sizes: list[int | None] = [None] + (
                    [64, 256, 1024] if label == "gpu" and n == max(ns.sfs_sizes) else []
                )
                for lsz in sizes:
                    key = label if lsz is None else f"{label}_local{lsz}"
                    try:
                        res = solve_opencl(problem, scheme, 1e-4, 8000, local_size=lsz, device=spec)
                        row[f"{key}_ms"] = best_ms(
                            lambda: solve_opencl(problem, scheme, 1e-4, 8000, local_size=lsz, device=spec),
                            1 if slow else ns.repeat,
                        )
                        row[f"{key}_max_diff"] = float(np.max(np.abs(res.z - ref.z)))
                        row[f"{key}_same_sweeps"] = res.sweeps == ref.sweeps
                    except Exception as exc:  # noqa: BLE001 - e.g. a local size over the device's limit
                        row[f"{key}_error"] = f"{type(exc).__name__}: {str(exc).splitlines()[0][:120]}"
                if label == "gpu":
                    # start-up: loads 6 modules of ours (24 ms here)
                    from nirspi_pipe.sfs.opencl import (
                        _program,
                        _program2,
                    )

                    kern = (
                        _program2(1, spec)[0]
                        if scheme == "second_order"
                        else _program(0, 0 if scheme == "lax_friedrichs" else 1, spec)
                    )
                    row["gpu_local_size"] = default_local_size(kern, spec, n, n)
            rows.append(row)
            print("  " + json.dumps(row))
            _save(ns, "sfs", {"rows": rows})
    if ns.gpu is None:
        print("  " + SKIP_NO_GPU + "SFS on the GPU")
    return {"rows": rows}


def part_fsrcnn(ns: argparse.Namespace) -> dict[str, Any]:
    # start-up: loads scipy, charset_normalizer (220 ms here)
    from nirspi_pipe.upscale.fsrcnn import (
        fsrcnn_forward,
        fsrcnn_forward_torch,
        load_weights,
    )

    img = np.random.default_rng(0).uniform(0, 1, (64, 64))
    w = load_weights(4)
    ref = fsrcnn_forward(img, w)
    out: dict[str, Any] = {"numpy_ms": best_ms(lambda: fsrcnn_forward(img, w), ns.repeat)}
    try:
        import torch  # optional dependency: torch
    except ImportError:
        print("  torch is not installed (pip install '.[train]'): torch parts skipped")
        return out
    out["torch"] = torch.__version__
    out["torch_cpu_ms"] = best_ms(lambda: fsrcnn_forward_torch(img, w, "cpu"), ns.repeat)
    out["torch_cpu_max_diff"] = float(np.max(np.abs(fsrcnn_forward_torch(img, w, "cpu") - ref)))
    if not torch.cuda.is_available():
        print("  " + SKIP_NO_GPU + "torch sees no CUDA: FSRCNN on CUDA")
        return out
    out["cuda_device"] = torch.cuda.get_device_name(0)
    for tf32 in (False, True):
        key = "cuda_tf32" if tf32 else "cuda"
        out[f"{key}_ms"] = best_ms(lambda: fsrcnn_forward_torch(img, w, "cuda", tf32), ns.repeat)  # ends with .cpu()
        out[f"{key}_max_diff"] = float(np.max(np.abs(fsrcnn_forward_torch(img, w, "cuda", tf32) - ref)))
    return out


def part_mesh3d(ns: argparse.Namespace) -> dict[str, Any]:
    out: dict[str, Any] = {}
    backends = ["numpy"] + (["opencl"] if ns.gpu is not None or ns.cpu is not None else [])
    for backend in backends:
        buf = io.StringIO()
        with contextlib.redirect_stdout(buf):
            mesh3d.main(["--resolution", "64", "--sfs", "second_order", "--sfs-backend", backend, "--repeat", "5"])
        text = buf.getvalue()
        print(text)
        stages = {m.group(1): float(m.group(2)) for m in re.finditer(r"^\s+(\w+)\s+([\d.]+)\s*$", text, re.M)}
        out[backend] = stages
    return out


PARTS = {"opencl": part_opencl, "omp": part_omp, "sfs": part_sfs, "fsrcnn": part_fsrcnn, "mesh3d": part_mesh3d}


# --- the driver ----------------------------------------------------------------------------------


def nvidia_icd_env(env: dict[str, str]) -> tuple[dict[str, str], str]:
    """``env`` with ``OCL_ICD_VENDORS`` pointing at NVIDIA's OpenCL library when no installed ICD
    names it; returns the environment and one line saying what was done."""
    vendors = Path("/etc/OpenCL/vendors")
    if any("nvidia" in p.read_text(errors="replace").lower() for p in vendors.glob("*.icd") if p.is_file()):
        return env, "NVIDIA ICD installed (/etc/OpenCL/vendors)"
    found: list[str] = []
    for pattern in (
        "/usr/local/nvidia/lib64/libnvidia-opencl.so.1",
        "/usr/local/nvidia/lib/libnvidia-opencl.so.1",
        "/usr/lib/x86_64-linux-gnu/libnvidia-opencl.so.1",
        "/usr/lib64/libnvidia-opencl.so.1",
        "/usr/lib/libnvidia-opencl.so.1",
    ):
        found += glob.glob(pattern)
    if not found:
        try:
            ldc = subprocess.run(["ldconfig", "-p"], capture_output=True, text=True, timeout=10).stdout
            found = [ln.split("=>")[-1].strip() for ln in ldc.splitlines() if "libnvidia-opencl.so.1" in ln]
        except (OSError, subprocess.SubprocessError):
            found = []
    if not found:
        return env, "no libnvidia-opencl.so.1 found: the ICD loader's defaults are left as they are"
    lib = found[0]
    # a private folder (mode 0700, a new name: tempfile.mkdtemp), never a fixed path in the shared
    # temp folder, where another user could plant a link or an ICD of their own (issue 41)
    folder = Path(tempfile.mkdtemp(prefix="nirspi-icd-"))
    atexit.register(shutil.rmtree, folder, True)
    (folder / "nvidia.icd").write_text(lib + "\n")
    env = dict(env, OCL_ICD_VENDORS=str(folder))
    libdir = str(Path(lib).parent)
    if libdir not in env.get("LD_LIBRARY_PATH", "").split(":"):
        env["LD_LIBRARY_PATH"] = libdir + (":" + env["LD_LIBRARY_PATH"] if env.get("LD_LIBRARY_PATH") else "")
    return env, f"OCL_ICD_VENDORS={folder} (only {lib})"


class Run:
    """Steps in children under one deadline; their JSON results and logs."""

    def __init__(self, out: Path, budget_s: float) -> None:
        self.out, self.t0, self.budget = out, time.monotonic(), budget_s
        self.results: dict[str, Any] = {}
        self.lines: list[str] = []

    def left(self) -> float:
        return self.budget - (time.monotonic() - self.t0)

    def say(self, line: str) -> None:
        print(line, flush=True)
        self.lines.append(line)

    def step(self, name: str, cmd: list[str], limit: float, env: dict[str, str]) -> int:
        t = min(limit, self.left() - 5)
        if t < 10:
            self.say(f"=== [{name}] SKIPPED: only {self.left():.0f} s of the {self.budget:.0f} s budget left")
            self.results[name] = {"skipped": "no time left"}
            return -1
        self.say(f"=== [{name}] at {time.monotonic() - self.t0:.0f} s, limit {t:.0f} s")
        log = self.out / f"{name}.log"
        start = time.monotonic()
        try:
            with open(log, "w") as fh:
                rc = subprocess.run(cmd, stdout=fh, stderr=subprocess.STDOUT, env=env, timeout=t).returncode
        except subprocess.TimeoutExpired:
            rc = 124
        text = log.read_text(errors="replace")
        sys.stdout.write(text)
        self.say(f"=== [{name}] rc={rc} after {time.monotonic() - start:.0f} s{' (TIMED OUT)' if rc == 124 else ''}")
        res_file = self.out / f"{name}.json"
        self.results[name] = json.loads(res_file.read_text()) if res_file.exists() else {"rc": rc}
        self.results[name]["rc"] = rc
        for line in text.splitlines():
            if SKIP_NO_GPU in line:
                self.lines.append(line.strip())
        return rc


def _f(value: Any, spec: str = ".1f") -> str:
    """A number formatted, ``-`` when there is none."""
    return "-" if not isinstance(value, (int, float)) else format(value, spec)


def _ratio(a: Any, b: Any) -> str:
    return "-" if not isinstance(a, (int, float)) or not isinstance(b, (int, float)) else f"{a / b:.3f}"


def _summary_md(res: dict[str, Any], head: list[str]) -> str:
    out = ["# nirspi-bench gpu", "", *head, ""]
    omp = res.get("omp", {})
    if omp.get("rows"):
        out += [
            "## OMP (25 % zig-zag, ImageTarget)",
            "",
            "| size | atoms | numpy ms | GPU ms | GPU/numpy | GPU max diff | GPU kernels ms | GPU workgroup ms "
            "| CPU device ms | CPU device max diff |",
            "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
        ]
        for r in omp["rows"]:
            out.append(
                f"| {r['size']}² | {r['atoms']} | {_f(r['numpy_ms'])} | {_f(r.get('gpu_ms'))} | "
                f"{_ratio(r.get('gpu_ms'), r['numpy_ms'])} | {_f(r.get('gpu_max_diff'), '.2g')} | "
                f"{_f(r.get('gpu_kernels_ms'))} | {_f(r.get('gpu_workgroup_ms'))} | "
                f"{_f(r.get('cpu_device_ms'))} | {_f(r.get('cpu_device_max_diff'), '.2g')} |"
            )
        b = omp.get("batch") or {}
        if b:
            out += [
                "",
                f"Batch: {b['problems']} problems of {b['size']}² in one device solve {_f(b['gpu_batch_ms'])} ms, "
                f"numpy one by one {_f(b['numpy_ms'])} ms, max diff {_f(b['max_diff'], '.2g')}",
            ]
        out.append("")
    sfs = res.get("sfs", {})
    if sfs.get("rows"):
        out += [
            "## SFS (sphere eikonal, tol 1e-4 px)",
            "",
            "| size | scheme | sweeps | numpy ms | GPU ms (local) | GPU/numpy | GPU max diff | CPU device ms | "
            "other GPU local sizes |",
            "|---|---|---:|---:|---:|---:|---:|---:|---|",
        ]
        for r in sfs["rows"]:
            extra = ", ".join(
                f"{k[len('gpu_local') : -3]}: {_f(v, '.2f')} ms"
                for k, v in r.items()
                if k.startswith("gpu_local") and k.endswith("_ms")
            )
            out.append(
                f"| {r['size']}² | {r['scheme']} | {r['sweeps']} | {_f(r['numpy_ms'])} | "
                f"{_f(r.get('gpu_ms'), '.2f')} ({r.get('gpu_local_size', '-')}) | {_ratio(r.get('gpu_ms'), r['numpy_ms'])} | "
                f"{_f(r.get('gpu_max_diff'), '.2g')} | {_f(r.get('cpu_device_ms'), '.2f')} | {extra or '-'} |"
            )
        out.append("")
    fs = res.get("fsrcnn", {})
    if "numpy_ms" in fs:
        body = dumps_strict({k: v for k, v in fs.items() if k != "rc"}, indent=1)
        out += ["## FSRCNN 64² → 256² (×4), ms and max |diff| against numpy", "", "```", body, "```", ""]
    m3 = res.get("mesh3d", {})
    if any(k in m3 for k in ("numpy", "opencl")):
        body = dumps_strict({k: v for k, v in m3.items() if k != "rc"}, indent=1)
        out += ["## 3D path at 64², second-order SFS (median ms per stage)", "", "```", body, "```", ""]
    par = res.get("parity", {})
    if "summary" in par:
        out += ["## Parity tests on the GPU", "", par["summary"], ""]
    return "\n".join(out) + "\n"


def table_rows(res: dict[str, Any], gpu_name: str | None) -> dict[str, dict[str, dict[int, str]]]:
    """Which back end was faster per stage and size on the GPU (for :func:`nirspi_pipe.opencl_devices.write_table`)."""
    if gpu_name is None:
        return {}
    rows: dict[str, dict[int, str]] = {}
    for r in res.get("omp", {}).get("rows", []):
        if "gpu_ms" in r and r.get("gpu_max_diff", 1.0) <= 1e-10:
            rows.setdefault("omp", {})[r["size"]] = "opencl" if r["gpu_ms"] < r["numpy_ms"] else "numpy"
    sfs: dict[int, list[bool]] = {}
    for r in res.get("sfs", {}).get("rows", []):
        if "gpu_ms" in r:
            sfs.setdefault(r["size"], []).append(r["gpu_ms"] < r["numpy_ms"])
    for size, faster in sfs.items():  # OpenCL only where it won for every scheme at that size
        rows.setdefault("sfs", {})[size] = "opencl" if all(faster) else "numpy"
    return {gpu_name: rows}


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="nirspi-bench gpu", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--out", default=os.environ.get("OUT", "gpu-check"), help="folder of the summary and logs")
    parser.add_argument("--budget", type=float, default=330.0, help="seconds for the whole check")
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--sfs-sizes", type=int, nargs="+", default=[64, 128, 256])
    parser.add_argument("--write-table", action="store_true", help="record the faster back ends for backend: auto")
    parser.add_argument("--part", choices=list(PARTS), help=argparse.SUPPRESS)
    parser.add_argument("--gpu", default=None, help=argparse.SUPPRESS)
    parser.add_argument("--cpu", default=None, help=argparse.SUPPRESS)
    return parser


def _nvidia_smi() -> str:
    """``nvidia-smi -L``'s listing, or "" without one."""
    try:
        return subprocess.run(["nvidia-smi", "-L"], capture_output=True, text=True, timeout=20).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return ""


#: The test modules the check runs on the GPU.
_PARITY_TESTS = (
    "test_parity.py",
    "test_sfs_opencl.py",
    "test_backend_auto.py",
    "test_omp.py",
    "test_fsrcnn_device.py",
    "test_bench_gpu.py",
)


def _parity_step(run: Run, gpu: dict[str, Any] | None, out: Path, env: dict[str, str]) -> None:
    """The parity tests on the GPU (from a source checkout's tests/), their summary line said."""
    tests = Path.cwd() / "tests"
    if gpu is None:
        run.say(SKIP_NO_GPU + "parity tests on the GPU")
        return
    if not (tests / "test_parity.py").exists():
        run.say("parity: SKIPPED (no tests/ here: run from a source checkout)")
        return
    cmd = [
        sys.executable,
        "-m",
        "pytest",
        "-q",
        "-p",
        "no:cacheprovider",
        "--continue-on-collection-errors",  # a test module whose imports fail here costs only itself
        "-m",
        "torch or not torch",
        "-k",
        "not remesh",
    ]
    cmd += [str(tests / t) for t in _PARITY_TESTS]
    run.step("parity", cmd, 120, env)
    text = (out / "parity.log").read_text(errors="replace")
    tail = re.findall(r"^=*\s*(\d+ (?:passed|failed).*?) in [\d.]+s", text, re.M)
    run.results["parity"]["summary"] = tail[-1] if tail else "no pytest summary line (timeout or crash?)"
    run.say(f"parity on {gpu['name']}: {run.results['parity']['summary']}")


def _write_summary(run: Run, out: Path, gpu: dict[str, Any] | None, cpu: dict[str, Any] | None, write: bool) -> None:
    """summary.json and summary.md, and (``write``) the device table of the faster back ends."""
    rows = table_rows(run.results, gpu["name"] if gpu else None)
    summary = {"head": run.lines, "gpu": gpu, "cpu_device": cpu, "results": run.results, "table_rows": rows}
    (out / "summary.json").write_text(dumps_strict(summary, indent=1))
    (out / "summary.md").write_text(_summary_md(run.results, [f"    {ln}" for ln in run.lines]))
    if write:
        if rows:
            print(f"device table: {write_table(rows)} <- {json.dumps(rows)}")
        else:
            print("device table: nothing measured on a GPU, left as it is")


def main(argv: list[str]) -> int:
    ns = _parser().parse_args(argv)
    out = Path(ns.out)
    out.mkdir(parents=True, exist_ok=True)
    if ns.part:  # a child: one part, its result as JSON
        result = PARTS[ns.part](ns)
        (out / f"{ns.part}.json").write_text(dumps_strict(result, indent=1))
        return 0

    run = Run(out, ns.budget)
    env = dict(os.environ, PYTHONUNBUFFERED="1", MPLBACKEND="Agg", OPENBLAS_NUM_THREADS="1")
    env, icd = nvidia_icd_env(env)
    run.say(f"nirspi-bench gpu, {time.strftime('%Y-%m-%dT%H:%M:%SZ', time.gmtime())}, {os.cpu_count()} CPU cores")
    run.say(icd)
    smi = _nvidia_smi()
    run.say(f"nvidia-smi: {smi or 'none'}")
    me = [sys.executable, "-m", "nirspi_pipe.benchmarks.gpu", "--out", str(out), "--repeat", str(ns.repeat)]
    run.step("opencl", [*me, "--part", "opencl"], 60, env)
    devs = run.results.get("opencl", {}).get("devices", [])
    gpu = next((d for d in devs if d["gpu"] and d["fp64"]), None)
    cpu = next((d for d in devs if not d["gpu"] and d["fp64"]), None)
    if gpu is None:
        run.say(SKIP_NO_GPU + "no OpenCL GPU with float64: the GPU columns stay empty, the CPU parts run")
    else:
        env["PYOPENCL_CTX"] = gpu["spec"]
        run.say(f"GPU: {gpu['platform']} / {gpu['name']} (PYOPENCL_CTX={gpu['spec']})")
    dev_args = (["--gpu", gpu["spec"]] if gpu else []) + (["--cpu", cpu["spec"]] if cpu else [])
    _parity_step(run, gpu, out, env)
    sizes = ["--sfs-sizes", *map(str, ns.sfs_sizes)]
    for name, limit in (("omp", 70), ("sfs", 110), ("fsrcnn", 40), ("mesh3d", 60)):
        run.step(name, [*me, "--part", name, *dev_args, *sizes], limit, env)
    run.say(f"done in {time.monotonic() - run.t0:.0f} s (budget {ns.budget:.0f} s)")
    _write_summary(run, out, gpu, cpu, ns.write_table)
    print(f"summary: {out / 'summary.md'}, {out / 'summary.json'}")
    return 0


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main(sys.argv[1:]))
