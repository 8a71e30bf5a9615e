"""Hostile files: NPZ recordings and weights, PLY/STL/OBJ meshes, images (docs/hostile.md).

Every case must give a correct result or a one-line NirspiError naming the file; none may crash,
hang or allocate beyond the read budget. Cases that reach native code run in a child process
(:func:`hostile_inputs.run_isolated`), so a segfault fails the test instead of killing pytest.
"""

from __future__ import annotations

import io
import struct
import zipfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from hostile_inputs import (
    npy_bytes,
    npz_bytes,
    obj_text,
    ply_ascii,
    ply_binary,
    png,
    recording_members,
    run_isolated,
    set_central_sizes,
    stl_binary,
    tetra,
)
from nirspi_pipe.device.recording import load_recording
from nirspi_pipe.errors import ConfigError, NirspiError
from nirspi_pipe.safeio import UnsafeInputError, read_npz
from nirspi_pipe.scene.meshfiles import MeshFileError, parse_mesh

FUZZ = settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])


def one_line(exc: BaseException) -> str:
    text = str(exc)
    assert "\n" not in text and text, text
    return text


# --------------------------------------------------------------------------- NPZ


def test_zip_bomb_is_refused_before_decompressing(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    # 64 MB of zeros deflate to ~64 kB; with a 16 MB budget the member is refused from its
    # declared size alone (the same check refuses the issue's 9.4 MB -> 4.7 GB file at 1 GiB).
    members = recording_members()
    members["itof_raw"] = npy_bytes(np.zeros(8 << 20))
    path = tmp_path / "bomb.npz"
    path.write_bytes(npz_bytes(members))
    assert path.stat().st_size < 200_000
    monkeypatch.setenv("NIRSPI_READ_BUDGET_MB", "16")
    with pytest.raises(UnsafeInputError) as err:
        load_recording(path)
    assert "bomb.npz" in one_line(err.value) and "itof_raw" in str(err.value) and "read budget" in str(err.value)


def test_the_default_read_budget_is_one_gib(monkeypatch: pytest.MonkeyPatch) -> None:
    """docs/hostile.md: 1 GiB unless ``NIRSPI_READ_BUDGET_MB`` says otherwise."""
    from nirspi_pipe.safeio import read_budget

    monkeypatch.delenv("NIRSPI_READ_BUDGET_MB", raising=False)
    assert read_budget() == 1 << 30
    monkeypatch.setenv("NIRSPI_READ_BUDGET_MB", "16")
    assert read_budget() == 16 << 20


def test_member_lying_about_its_size_names_the_key(tmp_path: Path) -> None:
    members = recording_members()
    data = npz_bytes(members)
    for declared in (10, len(members["image"]) + 4096):
        path = tmp_path / f"lie{declared}.npz"
        path.write_bytes(set_central_sizes(data, "image.npy", declared))
        with pytest.raises(NirspiError) as err:
            load_recording(path)
        assert f"lie{declared}.npz" in one_line(err.value) and "'image'" in str(err.value)


def test_corrupt_compressed_member_names_file_and_key(tmp_path: Path) -> None:
    data = bytearray(npz_bytes(recording_members()))
    info = zipfile.ZipFile(io.BytesIO(bytes(data))).getinfo("measurements.npy")
    start = info.header_offset + 30 + len("measurements.npy")
    for i in range(start + 5, start + info.compress_size - 5, 7):
        data[i] ^= 0x5A
    path = tmp_path / "corrupt.npz"
    path.write_bytes(bytes(data))
    with pytest.raises(NirspiError) as err:
        load_recording(path)
    assert "corrupt.npz" in one_line(err.value) and "'measurements'" in str(err.value)


def hdr(text: bytes) -> bytes:
    """A .npy v1.0 header around ``text`` (padded, newline-terminated)."""
    body = text.ljust(117) + b"\n"
    return b"\x93NUMPY\x01\x00" + struct.pack("<H", len(body)) + body


@pytest.mark.parametrize(
    "case,member,expect",
    [
        ("huge shape", hdr(b"{'descr': '<f8', 'fortran_order': False, 'shape': (1000000000, 1000000000), }"), "shape"),
        ("negative shape", hdr(b"{'descr': '<f8', 'fortran_order': False, 'shape': (-5,), }"), "shape"),
        ("object dtype", hdr(b"{'descr': '|O', 'fortran_order': False, 'shape': (1,), }"), "pickled"),
        ("bad magic", b"GARBAGE" * 20, "magic"),
        ("code in header", hdr(b"__import__('os').system('true')"), "header"),
    ],
)
def test_hostile_npy_headers_name_the_key(tmp_path: Path, case: str, member: bytes, expect: str) -> None:
    members = recording_members()
    members["measurements"] = member
    path = tmp_path / "h.npz"
    path.write_bytes(npz_bytes(members))
    with pytest.raises(NirspiError) as err:
        load_recording(path)
    assert "h.npz" in one_line(err.value) and "'measurements'" in str(err.value) and expect in str(err.value), case


def test_strings_from_a_recording_reach_the_terminal_sanitised(tmp_path: Path) -> None:
    import warnings

    members = recording_members()
    members["device"] = npy_bytes(np.array("\x1b[2Jrig\x07"))
    members["\x1b[31mevil"] = npy_bytes(np.zeros(1))
    path = tmp_path / "s.npz"
    path.write_bytes(npz_bytes(members))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        rec = load_recording(path)
    assert rec.meta["device"] == "?[2Jrig?"
    assert caught and all("\x1b" not in str(w.message) for w in caught)


@pytest.mark.parametrize("method", [zipfile.ZIP_BZIP2, zipfile.ZIP_LZMA])
def test_compression_methods_numpy_does_not_write_are_refused(tmp_path: Path, method: int) -> None:
    path = tmp_path / "m.npz"
    path.write_bytes(npz_bytes(recording_members(), method))
    with pytest.raises(UnsafeInputError, match="compression method .* allowed: stored or deflate"):
        load_recording(path)


def test_valid_recordings_still_load_compressed_and_stored(tmp_path: Path) -> None:
    for method in (zipfile.ZIP_STORED, zipfile.ZIP_DEFLATED):
        path = tmp_path / f"ok{method}.npz"
        path.write_bytes(npz_bytes(recording_members(), method))
        rec = load_recording(path)
        assert rec.n == 4 and rec.measurements.size == 32


@FUZZ
@given(data=st.data())
def test_fuzzed_npz_bytes_load_or_fail_with_one_line(tmp_path: Path, data: st.DataObject) -> None:
    good = bytearray(
        npz_bytes(recording_members(), data.draw(st.sampled_from([zipfile.ZIP_STORED, zipfile.ZIP_DEFLATED])))
    )
    action = data.draw(st.sampled_from(["truncate", "flip", "splice"]))
    if action == "truncate":
        good = good[: data.draw(st.integers(0, len(good) - 1))]
    elif action == "flip":
        for _ in range(data.draw(st.integers(1, 8))):
            i = data.draw(st.integers(0, len(good) - 1))
            good[i] = data.draw(st.integers(0, 255))
    else:
        i = data.draw(st.integers(0, len(good)))
        good[i:i] = data.draw(st.binary(min_size=1, max_size=64))
    path = tmp_path / "fuzz.npz"
    path.write_bytes(bytes(good))
    try:
        rec = load_recording(path)
    except NirspiError as exc:
        assert "fuzz.npz" in one_line(exc)
    else:
        assert np.all(np.isfinite(rec.measurements))


@pytest.mark.parametrize("exponent", [300, 200, -300])
def test_recording_scaled_by_huge_factors_is_finite_or_a_clear_error(tmp_path: Path, exponent: int) -> None:
    from hydra import compose, initialize_config_module

    from nirspi_pipe.app.jobs import execute_job
    from nirspi_pipe.finite import is_finite_tree

    path = tmp_path / "scaled.npz"
    path.write_bytes(npz_bytes(recording_members(8, 10.0**exponent)))
    with initialize_config_module("nirspi_pipe.conf", version_base="1.3"):
        cfg = compose("config", overrides=["source=recorded", f"source.path={path}", "camera.resolution=8"])
    rec = execute_job(cfg, tmp_path / "out", {}, [])
    if rec["meta"]["status"] == "ok":
        assert all(is_finite_tree(rec[k]) for k in ("metrics", "derived", "info", "timings_ms"))
        assert exponent < 151  # max_safe_reading(128, 64) = 1.3e151 for this 8x8 recording
    else:
        assert "scaled.npz" in rec["meta"]["error"] and "'measurements'" in rec["meta"]["error"]
        assert "overflow" in rec["meta"]["error"] and exponent > 0


# --------------------------------------------------------------------------- meshes


def _mesh_cases(tmp: Path) -> dict[str, tuple[Path, str]]:
    """name -> (file, substring the error must contain, or "" for a valid mesh)."""
    v, f = tetra()
    bad_face = f.copy()
    bad_face[2, 1] = 99
    cases = {
        "ply 1e8 vertices (278 bytes)": (ply_binary(v, f, nv=100_000_000), "declares 100000000 vertex"),
        "ply 1e9 vertices": (ply_binary(v, f, nv=1_000_000_000), "declares 1000000000 vertex"),
        "ply 1e9 faces": (ply_binary(v, f, nf=1_000_000_000), "face element"),
        "ply face index out of range": (ply_binary(v, bad_face), "face 2 uses vertex [0, 99, 2], out of range [0, 4)"),
        "ply ascii face index out of range": (ply_ascii(v, bad_face), "face 2 uses vertex"),
        "ply no end_header": (b"ply\nformat ascii 1.0\n" + b"comment x\n" * 10_000, "end_header"),
        "ply unknown format": (PLY_BAD_FORMAT, "format"),
        "ply negative list count": (ply_binary(v, f)[:-52] + bytes([255]) + ply_binary(v, f)[-51:], ""),
        "stl count larger than file": (stl_binary(v, f, declared=50_000_000), "declares 50000000 triangles"),
        "obj index out of range": (obj_text(v, bad_face), "face 2 uses vertex"),
        "obj vertex index 0": (b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 0 1 2\n", "index 0"),
        "obj nan vertex": (b"v nan 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n", "not finite"),
        "ply valid": (ply_binary(v, f), None),
        "ply ascii valid": (ply_ascii(v, f), None),
        "stl valid": (stl_binary(v, f), None),
        "obj valid": (obj_text(v, f), None),
        "random bytes ply": (np.random.default_rng(1).bytes(300), "not a PLY"),
    }
    out = {}
    for i, (name, (data, expect)) in enumerate(cases.items()):
        ext = name.split()[0] if name.split()[0] in ("ply", "stl", "obj") else "ply"
        if name.startswith("random"):
            ext = "ply"
        path = tmp / f"case{i}.{ext}"
        path.write_bytes(data)
        out[name] = (path, expect)
    return out


PLY_BAD_FORMAT = b"ply\nformat binary_middle_endian 1.0\nelement vertex 3\nend_header\n"


def test_hostile_mesh_files_in_a_child_process(tmp_path: Path) -> None:
    cases = _mesh_cases(tmp_path)
    results = {r["path"]: r for r in run_isolated("mesh", [p for p, _ in cases.values()])}
    for name, (path, expect) in cases.items():
        r = results[str(path)]
        assert r["result"] != "crash", (name, r)
        if expect is None:
            assert r["result"] == "ok", (name, r)
        elif expect:
            assert r["result"] == "error" and path.name in r["message"] and expect in r["message"], (name, r)
            assert "\n" not in r["message"]


def test_the_issue_ply_gives_a_one_line_error_from_nirspi_run(tmp_path: Path) -> None:
    from conftest import run_cli

    v, f = tetra()
    data = ply_binary(v, f, nv=100_000_000)
    (tmp_path / "tiny.ply").write_bytes(data)
    res = run_cli(["nirspi-run", "scene=mesh", "scene.path=tiny.ply", "camera.resolution=8"], tmp_path, timeout=120)
    assert res.returncode == 2, (res.returncode, res.stderr[-2000:])
    err = res.stderr.strip().splitlines()
    assert len(err) == 1 and "scene.path=" in err[0] and "tiny.ply" in err[0] and "100000000" in err[0], err


@FUZZ
@given(data=st.data())
def test_fuzzed_mesh_bytes_parse_or_fail_with_one_line(data: st.DataObject) -> None:
    v, f = tetra()
    ext = data.draw(st.sampled_from([".ply", ".stl", ".obj"]))
    make = {".ply": data.draw(st.sampled_from([ply_binary, ply_ascii])), ".stl": stl_binary, ".obj": obj_text}[ext]
    raw = bytearray(make(v, f))
    for _ in range(data.draw(st.integers(0, 6))):
        op = data.draw(st.sampled_from(["flip", "cut", "insert"]))
        if op == "flip" and raw:
            raw[data.draw(st.integers(0, len(raw) - 1))] = data.draw(st.integers(0, 255))
        elif op == "cut":
            raw = raw[: data.draw(st.integers(0, len(raw)))]
        else:
            i = data.draw(st.integers(0, len(raw)))
            raw[i:i] = data.draw(
                st.sampled_from([b"9999999999", b"-1", b"\n", b"element face 5\n", b"nan", b"\xff" * 4])
            )
    try:
        verts, faces = parse_mesh(bytes(raw), ext, "mesh file fuzz" + ext, budget=64 << 20)
    except (MeshFileError, UnsafeInputError) as exc:
        assert "fuzz" in one_line(exc)
    else:
        assert np.isfinite(verts).all() and faces.min() >= 0 and faces.max() < len(verts)


def test_mesh_behind_the_camera_names_the_distance(tmp_path: Path) -> None:
    from nirspi_pipe.scene.shapes import MeshScene
    from nirspi_pipe.types import Camera

    v, f = tetra()
    path = tmp_path / "t.ply"
    path.write_bytes(ply_binary(v * 500, f))  # 500 mm across at scale 1: reaches behind the pinhole
    with pytest.raises(ConfigError) as err:
        MeshScene(path=str(path), size_mm=None, scale=1.0, distance_mm=200.0).render(Camera(8))
    msg = one_line(err.value)
    assert "distance_mm=200.0" in msg and "None" not in msg and "in front of the camera" in msg


# --------------------------------------------------------------------------- images and weights


def test_hostile_images_in_a_child_process(tmp_path: Path) -> None:
    from PIL import Image

    cases = {
        "bomb.png": (png(100_000, 100_000), "a readable image"),
        "big.png": (png(8_000, 8_000), "read budget"),
        "truncated.png": (png(64, 64)[:40], "a readable image"),
        "random.png": (np.random.default_rng(2).bytes(500), "a readable image"),
        "empty.png": (b"", "a readable image"),
    }
    paths = []
    for name, (data, _) in cases.items():
        (tmp_path / name).write_bytes(data)
        paths.append(tmp_path / name)
    Image.fromarray(np.arange(64, dtype=np.uint8).reshape(8, 8)).save(tmp_path / "ok.png")
    paths.append(tmp_path / "ok.png")
    results = {Path(r["path"]).name: r for r in run_isolated("image", paths, budget_mb=256)}
    assert results["ok.png"]["result"] == "ok"
    for name, (_, expect) in cases.items():
        r = results[name]
        assert r["result"] == "error" and name in r["message"] and expect in r["message"], (name, r)


def test_hostile_weights_in_a_child_process(tmp_path: Path) -> None:
    from nirspi_pipe.upscale.fsrcnn import packaged_weights_path

    good = read_npz(packaged_weights_path(2), mmap=False)
    cases = {}
    wrong_shape = dict(good)
    wrong_shape["conv1_w"] = np.zeros((3, 3, 3, 3), np.float32)
    cases["shape.npz"] = {k: npy_bytes(v) for k, v in wrong_shape.items()}
    nan = dict(good)
    nan["deconv_b"] = np.array([np.nan], np.float32)
    cases["nan.npz"] = {k: npy_bytes(v) for k, v in nan.items()}
    bomb = {k: npy_bytes(v) for k, v in good.items()}
    bomb["conv0_w"] = npy_bytes(np.zeros((4096, 1, 64, 64), np.float32))  # 64 MB of zeros
    cases["bomb.npz"] = bomb
    paths = []
    for name, members in cases.items():
        (tmp_path / name).write_bytes(npz_bytes(members))
        paths.append(tmp_path / name)
    for r in run_isolated("weights", paths):
        assert r["result"] == "error" and "weights=" in r["message"] and Path(r["path"]).name in r["message"], r
