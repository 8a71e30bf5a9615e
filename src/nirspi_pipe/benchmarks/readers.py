"""``nirspi-bench readers``: the bounded readers against the libraries they replace, same process.

* NPZ: :func:`nirspi_pipe.safeio.read_npz` against ``numpy.load`` (every member read into
  memory, both compressed and stored), on a recording-sized file.
* Mesh: :func:`nirspi_pipe.scene.meshfiles.read_mesh_file` against ``pyvista.read`` on the same
  binary PLY, binary STL and OBJ (a sphere of about 80k triangles).

Prints the median of ``--repeat`` runs of each and the ratio ours / reference (> 1: ours slower).
"""

from __future__ import annotations

import argparse
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from nirspi_pipe.safeio import read_npz
from nirspi_pipe.scene.meshfiles import read_mesh_file


def _median_s(fn: Callable[[], Any], repeat: int) -> float:
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times))


def _np_load_all(path: Path) -> dict[str, np.ndarray]:
    with np.load(path, allow_pickle=False) as z:
        return {k: z[k] for k in z.files}


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="nirspi-bench readers", description=(__doc__ or "").split("\n\n")[0])
    parser.add_argument("--repeat", type=int, default=5, help="repetitions (median)")
    parser.add_argument("--mb", type=float, default=64.0, help="size of the NPZ's main array, MB")
    parser.add_argument("--resolution", type=int, default=200, help="sphere theta/phi resolution of the mesh")
    ns = parser.parse_args(argv)
    if ns.repeat < 1:  # a median of no repetition printed nan (issue 41)
        parser.error(f"--repeat {ns.repeat} is not allowed; allowed: an integer >= 1")
    if not (np.isfinite(ns.mb) and 0 < ns.mb <= 4096):
        parser.error(f"--mb {ns.mb} is not allowed; allowed: a size in MB in (0, 4096]")
    if ns.resolution < 3:
        parser.error(f"--resolution {ns.resolution} is not allowed; allowed: an integer >= 3")
    rng = np.random.default_rng(0)
    with tempfile.TemporaryDirectory() as tmp:
        big = rng.integers(0, 2, size=int(ns.mb * 1e6 / 8)).astype(np.float64)  # 0/1 patterns
        for name, save in (("stored", np.savez), ("deflate", np.savez_compressed)):
            path = Path(tmp) / f"{name}.npz"
            save(path, patterns=big, measurements=rng.random(1000))
            ours = _median_s(lambda: {k: np.asarray(v).sum() for k, v in read_npz(path, mmap=False).items()}, ns.repeat)
            ref = _median_s(lambda: {k: v.sum() for k, v in _np_load_all(path).items()}, ns.repeat)
            print(
                f"npz {name:8s} {path.stat().st_size / 1e6:7.1f} MB: read_npz {ours:.3f} s, numpy.load {ref:.3f} s, "
                f"ratio {ours / ref:.2f}"
            )
        import pyvista as pv  # start-up: loads pyvista (357 ms here)

        mesh = pv.Sphere(theta_resolution=ns.resolution, phi_resolution=ns.resolution)
        for ext in (".ply", ".stl", ".obj"):
            path = Path(tmp) / f"sphere{ext}"
            mesh.save(str(path))
            ours = _median_s(lambda: read_mesh_file(path), ns.repeat)
            ref = _median_s(lambda: pv.read(str(path)), ns.repeat)
            print(
                f"mesh {ext:5s} {mesh.n_cells} triangles, {path.stat().st_size / 1e6:.1f} MB: ours {ours:.3f} s, "
                f"pyvista.read {ref:.3f} s, ratio {ours / ref:.2f}"
            )
    return 0
