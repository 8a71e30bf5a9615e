"""Triangle mesh files (PLY, STL, OBJ) read by a small numpy parser of our own.

Native readers (VTK through pyvista) trust the counts a header declares: a 278-byte PLY that
announces 10⁸ vertices makes them allocate gigabytes or crash the process. This parser checks
every declared count against the bytes the file really holds and against the memory budget
(:mod:`nirspi_pipe.safeio`) before it allocates, checks every face index against the vertex
count, and raises :class:`MeshFileError` (one line naming the file) on anything else.

Supported: PLY 1.0 (``ascii``, ``binary_little_endian``, ``binary_big_endian``; a ``vertex``
element with ``x y z``, a ``face`` element with a list property ``vertex_indices`` or
``vertex_index``; other elements and properties are skipped), STL (binary and ASCII; identical
corner positions are merged into one vertex), OBJ (``v`` and ``f`` lines, ``a/b/c`` corners,
negative relative indices; everything else is ignored). Polygons are fan-triangulated.
"""

from __future__ import annotations

import re
import warnings
from pathlib import Path
from typing import Any

import numpy as np

from nirspi_pipe.errors import NirspiError
from nirspi_pipe.safeio import check_budget, read_budget, sanitize_text

__all__ = ["MESH_SUFFIXES", "MeshFileError", "parse_mesh", "read_mesh_file"]

MESH_SUFFIXES = (".ply", ".stl", ".obj")

_PLY_TYPES = {
    "char": "i1",
    "int8": "i1",
    "uchar": "u1",
    "uint8": "u1",
    "short": "i2",
    "int16": "i2",
    "ushort": "u2",
    "uint16": "u2",
    "int": "i4",
    "int32": "i4",
    "uint": "u4",
    "uint32": "u4",
    "float": "f4",
    "float32": "f4",
    "double": "f8",
    "float64": "f8",
}
_MAX_HEADER = 65536
_MAX_POLYGON = 1024  # assumed: corners per face; real polygons have a handful, and a fan of 1024 is 1022 triangles
#: Peak bytes of Python objects per byte of text while parsing ASCII PLY and OBJ files. Measured
#: with tracemalloc on ``pyvista.Sphere(theta_resolution=400, phi_resolution=400)`` saved as OBJ
#: (33.5 MB: peak 5.3×) and as ASCII PLY (26.8 MB: peak 7.9×); rounded up.
_TEXT_FACTOR = 8


class MeshFileError(NirspiError, ValueError):
    """A mesh file is malformed or declares more than it holds."""


def _fail(where: str, problem: str) -> MeshFileError:
    return MeshFileError(f"{where}: {problem}")


def read_mesh_file(path: str | Path, budget: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """``(vertices (v, 3) float64, faces (f, 3) int64)`` of a ``.ply``/``.stl``/``.obj`` file."""
    file = Path(path)
    where = f"mesh file {path}"
    suffix = file.suffix.lower()
    if suffix not in MESH_SUFFIXES:
        raise _fail(where, f"format {suffix or '(none)'!r} is not allowed; allowed: {', '.join(MESH_SUFFIXES)}")
    try:
        size = file.stat().st_size
        check_budget(size, "reading the file", where, budget)
        data = file.read_bytes()
    except OSError as exc:
        raise _fail(where, f"cannot be read ({exc.strerror or exc})") from None
    return parse_mesh(data, suffix, where, budget)


def parse_mesh(data: bytes, suffix: str, where: str, budget: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Parse mesh bytes of format ``suffix`` (``.ply``, ``.stl``, ``.obj``); see the module doc."""
    limit = read_budget(budget)
    if suffix == ".ply":
        verts, faces = _ply(data, where, limit)
    elif suffix == ".stl":
        verts, faces = _stl(data, where, limit)
    elif suffix == ".obj":
        verts, faces = _obj(data, where, limit)
    else:
        raise _fail(where, f"format {suffix!r} is not allowed; allowed: {', '.join(MESH_SUFFIXES)}")
    if faces.shape[0] == 0:
        raise _fail(where, "no triangles (a mesh with at least one triangle is needed)")
    if verts.shape[0] == 0:
        raise _fail(where, "no vertices")
    if not np.all(np.isfinite(verts)):
        bad = int(np.argmax(~np.isfinite(verts).all(axis=1)))
        raise _fail(where, f"vertex {bad} is not finite ({verts[bad].tolist()})")
    bad_face = np.flatnonzero((faces < 0).any(axis=1) | (faces >= verts.shape[0]).any(axis=1))
    if bad_face.size:
        f = int(bad_face[0])
        raise _fail(
            where,
            f"face {f} uses vertex {faces[f].tolist()}, out of range [0, {verts.shape[0]}) "
            f"({bad_face.size} such face(s))",
        )
    return verts, faces


def _fan(polys: list[list[int]] | np.ndarray) -> np.ndarray:
    """Fan-triangulate polygons (each a sequence of ≥ 3 vertex indices)."""
    tris = [(p[0], p[i], p[i + 1]) for p in polys for i in range(1, len(p) - 1)]
    return np.asarray(tris, dtype=np.int64).reshape(-1, 3)


# ---------------------------------------------------------------------------------------------
# PLY


_PlyElements = list[tuple[str, int, list[tuple[str, ...]]]]


def _ply_format(tok: list[str], line: str, no: int, where: str) -> str:
    """A header's ``format`` line: its format, one of the three PLY allows."""
    if len(tok) != 3 or tok[1] not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise _fail(
            where,
            f"header line {no}: format {sanitize_text(line, 60)!r} is not allowed; "
            "allowed: ascii, binary_little_endian, binary_big_endian",
        )
    return tok[1]


def _ply_property(tok: list[str], line: str, no: int, elements: _PlyElements, where: str) -> None:
    """A header's ``property`` line, appended to the last element's properties."""
    if not elements:
        raise _fail(where, f"header line {no}: property before any element")
    if len(tok) == 3 and tok[1] in _PLY_TYPES:
        elements[-1][2].append((tok[2], _PLY_TYPES[tok[1]]))
    elif len(tok) == 5 and tok[1] == "list" and tok[2] in _PLY_TYPES and tok[3] in _PLY_TYPES:
        if _PLY_TYPES[tok[2]][0] == "f":
            raise _fail(where, f"header line {no}: a list count must be an integer type")
        elements[-1][2].append((tok[4], "list", _PLY_TYPES[tok[2]], _PLY_TYPES[tok[3]]))
    else:
        raise _fail(
            where,
            f"header line {no}: unreadable property {sanitize_text(line, 60)!r} "
            f"(types: {', '.join(sorted(_PLY_TYPES))})",
        )


def _ply_header(data: bytes, where: str) -> tuple[str, _PlyElements, int]:
    if not data.startswith(b"ply"):
        raise _fail(where, "not a PLY file (it must start with 'ply')")
    m = re.search(rb"end_header[ \t]*\r?\n", data[:_MAX_HEADER])
    if m is None:
        raise _fail(where, f"no 'end_header' line in the first {_MAX_HEADER} bytes")
    lines = data[: m.start()].decode("ascii", errors="replace").splitlines()[1:]
    fmt = None
    elements: _PlyElements = []
    for no, line in enumerate(lines, start=2):
        tok = line.split()
        if not tok or tok[0] in ("comment", "obj_info"):
            continue
        if tok[0] == "format":
            fmt = _ply_format(tok, line, no, where)
        elif tok[0] == "element":
            if len(tok) != 3 or not tok[2].isdigit():
                raise _fail(where, f"header line {no}: expected 'element NAME COUNT', got {sanitize_text(line, 60)!r}")
            elements.append((tok[1], int(tok[2]), []))
        elif tok[0] == "property":
            _ply_property(tok, line, no, elements, where)
        else:
            raise _fail(where, f"header line {no}: unknown keyword {sanitize_text(tok[0], 30)!r}")
    if fmt is None:
        raise _fail(where, "no 'format' line in the header")
    return fmt, elements, m.end()


def _ply_check_elements(elements: _PlyElements, where: str) -> list[str]:
    """The element names, once there is a vertex element with x, y, z and a face element
    with a list of vertex indices."""
    names = [e[0] for e in elements]
    if "vertex" not in names or "face" not in names:
        raise _fail(where, f"needs 'vertex' and 'face' elements, has {', '.join(names) or 'none'}")
    vprops = [p[0] for p in elements[names.index("vertex")][2]]
    if not {"x", "y", "z"} <= set(vprops):
        raise _fail(where, "element 'vertex' needs properties x, y and z")
    fprops = elements[names.index("face")][2]
    if not any(p[0] in ("vertex_indices", "vertex_index") and p[1] == "list" for p in fprops):
        raise _fail(where, "element 'face' needs a list property vertex_indices")
    return names


def _ply_check_sizes(fmt: str, elements: _PlyElements, body: int, where: str) -> None:
    """Declared counts against the ``body`` bytes present, before anything is allocated."""
    need = 0
    for name, count, props in elements:
        if fmt == "ascii":
            per = 2 * len(props)  # each value takes a digit and a separator at least
        else:
            per = sum(np.dtype(p[2]).itemsize if p[1] == "list" else np.dtype(p[1]).itemsize for p in props)
            if name == "face":
                per += 3 * max((np.dtype(p[3]).itemsize for p in props if p[1] == "list"), default=0)
        need += count * per
        if need > body:
            raise _fail(
                where,
                f"header declares {count} {name} element(s) needing at least {need} bytes, "
                f"the file holds {body} after its header (truncated or a hostile header)",
            )


def _ply(data: bytes, where: str, limit: int) -> tuple[np.ndarray, np.ndarray]:
    fmt, elements, pos = _ply_header(data, where)
    names = _ply_check_elements(elements, where)
    body = len(data) - pos
    _ply_check_sizes(fmt, elements, body, where)
    nv = elements[names.index("vertex")][1]
    nf = elements[names.index("face")][1]
    check_budget(nv * 3 * 8 + nf * 3 * 8 * 2, f"{nv} vertices and {nf} faces", where, limit)
    if fmt == "ascii":
        check_budget(body * _TEXT_FACTOR, "parsing the ASCII body", where, limit)
        return _ply_ascii(data[pos:], elements, where)
    endian = "<" if fmt == "binary_little_endian" else ">"
    out: dict[str, np.ndarray] = {}
    for name, count, props in elements:
        arr, pos = _ply_binary_element(data, pos, name, count, props, endian, where)
        if name in ("vertex", "face"):
            out[name] = arr
    return out["vertex"], out["face"]


def _ply_binary_element(
    data: bytes, pos: int, name: str, count: int, props: list[tuple[str, ...]], endian: str, where: str
) -> tuple[np.ndarray, int]:
    """One element's rows → (vertices (count, 3) | triangles (t, 3) | empty, new position)."""
    lists = [p for p in props if p[1] == "list"]
    if not lists:
        dt = np.dtype([(f"p{i}_{p[0]}", endian + p[1]) for i, p in enumerate(props)])
        if pos + count * dt.itemsize > len(data):
            raise _fail(where, f"element '{name}': {count} rows of {dt.itemsize} bytes run past the end of the file")
        rows = np.frombuffer(data, dtype=dt, count=count, offset=pos)
        pos += count * dt.itemsize
        if name == "vertex":
            cols = {p[0]: f"p{i}_{p[0]}" for i, p in enumerate(props)}
            return np.column_stack([rows[cols[c]].astype(np.float64) for c in "xyz"]), pos
        return np.zeros((0, 3)), pos
    if name == "face" and len(lists) == 1:
        fast = _ply_uniform_faces(data, pos, count, props, endian)
        if fast is not None:
            return fast
    return _ply_rows(data, pos, name, count, props, endian, where)


def _ply_uniform_faces(
    data: bytes, pos: int, count: int, props: list[tuple[str, ...]], endian: str
) -> tuple[np.ndarray, int] | None:
    """Fast path: every face has the same corner count ``k`` (all triangles, say)."""
    if count == 0:
        return np.zeros((0, 3), np.int64), pos
    off = pos
    for p in props:  # the first row's list count
        if p[1] == "list":
            cdt = np.dtype(endian + p[2])
            if off + cdt.itemsize > len(data):
                return None
            k = int(np.frombuffer(data, dtype=cdt, count=1, offset=off)[0])
            break
        off += np.dtype(p[1]).itemsize
    if not 3 <= k <= _MAX_POLYGON:
        return None
    fields: list[tuple[Any, ...]] = []
    for i, p in enumerate(props):
        if p[1] == "list":
            fields += (
                [("count", endian + p[2]), ("idx", endian + p[3], (k,))]
                if p[0] in ("vertex_indices", "vertex_index")
                else [(f"c{i}", endian + p[2]), (f"l{i}", endian + p[3], (k,))]
            )
        else:
            fields.append((f"p{i}", endian + p[1]))
    dt = np.dtype(fields)
    if pos + count * dt.itemsize > len(data):
        return None
    rows = np.frombuffer(data, dtype=dt, count=count, offset=pos)
    if not np.all(rows["count"] == k) or any(str(f[0]).startswith("c") and not np.all(rows[f[0]] == k) for f in fields):
        return None
    idx = rows["idx"].astype(np.int64)
    tris = np.concatenate([idx[:, [0, i, i + 1]] for i in range(1, k - 1)]) if k > 3 else idx
    return tris, pos + count * dt.itemsize


def _ply_rows(
    data: bytes, pos: int, name: str, count: int, props: list[tuple[str, ...]], endian: str, where: str
) -> tuple[np.ndarray, int]:
    """General binary rows, one at a time (bounded: each row consumes at least one byte)."""
    polys: list[list[int]] = []
    verts: list[list[float]] = []
    n = len(data)
    for r in range(count):
        values: dict[str, object] = {}
        for p in props:
            if p[1] == "list":
                cdt, idt = np.dtype(endian + p[2]), np.dtype(endian + p[3])
                if pos + cdt.itemsize > n:
                    raise _fail(where, f"element '{name}' row {r}: truncated")
                k = int(np.frombuffer(data, dtype=cdt, count=1, offset=pos)[0])
                pos += cdt.itemsize
                if k < 0 or pos + k * idt.itemsize > n:
                    raise _fail(where, f"element '{name}' row {r}: list of {k} items runs past the end of the file")
                values[p[0]] = np.frombuffer(data, dtype=idt, count=k, offset=pos)
                pos += k * idt.itemsize
            else:
                dt = np.dtype(endian + p[1])
                if pos + dt.itemsize > n:
                    raise _fail(where, f"element '{name}' row {r}: truncated")
                values[p[0]] = np.frombuffer(data, dtype=dt, count=1, offset=pos)[0]
                pos += dt.itemsize
        if name == "face":
            corners = values.get("vertex_indices", values.get("vertex_index"))
            polys.append(_corners(corners, r, where))
        elif name == "vertex":
            verts.append([float(values[c]) for c in "xyz"])  # type: ignore[arg-type]
    if name == "face":
        return _fan(polys), pos
    if name == "vertex":
        return np.asarray(verts, dtype=np.float64).reshape(-1, 3), pos
    return np.zeros((0, 3)), pos


def _corners(corners: object, r: int, where: str) -> list[int]:
    c = [int(i) for i in np.asarray(corners).ravel()]
    if not 3 <= len(c) <= _MAX_POLYGON:
        raise _fail(where, f"face {r} has {len(c)} corners (allowed: 3 to {_MAX_POLYGON})")
    return c


def _ply_ascii_vertices(rows: list[bytes], count: int, props: list[tuple[str, ...]], where: str) -> np.ndarray:
    """The ASCII vertex rows' x, y, z columns ``(count, 3)``."""
    if any(p[1] == "list" for p in props):
        raise _fail(where, "element 'vertex': list properties are not supported")
    vals = _numbers(b" ".join(rows), count * len(props), where, "vertex")
    cols = [p[0] for p in props]
    table = vals.reshape(count, len(props))
    return table[:, [cols.index(c) for c in "xyz"]]


def _ply_ascii_face(row: bytes, props: list[tuple[str, ...]], li: int) -> list[int]:
    """One ASCII face row's corners (``li``: the index property's place); ValueError or
    IndexError when the row does not read."""
    tok = row.split()
    skip = 0
    for p in props[:li]:  # scalar or list properties before the indices
        skip += 1 + int(tok[skip]) if p[1] == "list" else 1
    k = int(tok[skip])
    if not 3 <= k <= _MAX_POLYGON or len(tok) < skip + 1 + k:
        raise ValueError
    return [int(t) for t in tok[skip + 1 : skip + 1 + k]]


def _ply_ascii_faces(rows: list[bytes], props: list[tuple[str, ...]], where: str) -> np.ndarray:
    """The ASCII face rows, fan-triangulated."""
    li = next(i for i, p in enumerate(props) if p[1] == "list" and p[0] in ("vertex_indices", "vertex_index"))
    polys = []
    for r, row in enumerate(rows):
        try:
            polys.append(_ply_ascii_face(row, props, li))
        except (ValueError, IndexError):
            raise _fail(where, f"face {r}: unreadable row {sanitize_text(row.decode('latin1'), 60)!r}") from None
    return _fan(polys)


def _ply_ascii(body: bytes, elements: _PlyElements, where: str) -> tuple[np.ndarray, np.ndarray]:
    lines = [ln for ln in body.split(b"\n") if ln.strip()]
    at = 0
    out: dict[str, np.ndarray] = {}
    for name, count, props in elements:
        if at + count > len(lines):
            raise _fail(where, f"element '{name}': header declares {count} rows, the file has {len(lines) - at} left")
        rows = lines[at : at + count]
        at += count
        if name == "vertex":
            out["vertex"] = _ply_ascii_vertices(rows, count, props, where)
        elif name == "face":
            out["face"] = _ply_ascii_faces(rows, props, where)
    return out["vertex"], out["face"]


def _numbers(text: bytes, expected: int, where: str, what: str) -> np.ndarray:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:  # unmatched data: a DeprecationWarning in older numpy, a ValueError in newer
            vals = np.fromstring(text.decode("latin1"), dtype=np.float64, sep=" ")
        except ValueError:
            raise _fail(where, f"{what} rows: a value that is not a number (a malformed row)") from None
    if vals.size != expected:
        raise _fail(where, f"{what} rows: expected {expected} numbers, read {vals.size} (a malformed row)")
    return vals


# ---------------------------------------------------------------------------------------------
# STL

_STL_DTYPE = np.dtype([("normal", "<f4", (3,)), ("v", "<f4", (3, 3)), ("attr", "<u2")])


def _merge(corners: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(t, 3, 3)`` triangle corners → unique vertices and ``(t, 3)`` faces."""
    flat = corners.reshape(-1, 3).astype(np.float64)
    verts, inverse = np.unique(flat, axis=0, return_inverse=True)
    return verts, inverse.reshape(-1, 3).astype(np.int64)


def _stl(data: bytes, where: str, limit: int) -> tuple[np.ndarray, np.ndarray]:
    if len(data) >= 84:
        count = int.from_bytes(data[80:84], "little")
        if 84 + 50 * count == len(data) or (not data.lstrip().startswith(b"solid") and 84 + 50 * count <= len(data)):
            check_budget(count * 9 * 8 * 3, f"{count} triangles", where, limit)
            tri = np.frombuffer(data, dtype=_STL_DTYPE, count=count, offset=84)
            return _merge(tri["v"])
        if not data.lstrip().startswith(b"solid"):
            raise _fail(
                where,
                f"binary STL header declares {count} triangles ({84 + 50 * count} bytes), "
                f"the file has {len(data)} bytes",
            )
    if not data.lstrip().startswith(b"solid"):
        raise _fail(where, "not an STL file (binary: 84-byte header; ASCII: starts with 'solid')")
    check_budget(len(data) * _TEXT_FACTOR, "parsing the ASCII STL", where, limit)
    nums = re.findall(rb"vertex\s+(\S+)\s+(\S+)\s+(\S+)", data)
    if len(nums) % 3:
        raise _fail(where, f"{len(nums)} vertex lines, not a multiple of 3 (a truncated facet)")
    try:
        corners = np.array(nums, dtype=np.float64).reshape(-1, 3, 3)
    except ValueError:
        raise _fail(where, "a vertex line holds something other than three numbers") from None
    return _merge(corners)


# ---------------------------------------------------------------------------------------------
# OBJ


def _obj(data: bytes, where: str, limit: int) -> tuple[np.ndarray, np.ndarray]:
    check_budget(len(data) * _TEXT_FACTOR, "parsing the OBJ text", where, limit)
    verts: list[tuple[float, float, float]] = []
    polys: list[list[int]] = []
    for no, raw in enumerate(data.split(b"\n"), start=1):
        tok = raw.split()
        if not tok:
            continue
        if tok[0] == b"v":
            try:
                verts.append((float(tok[1]), float(tok[2]), float(tok[3])))
            except (ValueError, IndexError):
                raise _fail(where, f"line {no}: a 'v' line needs three numbers") from None
        elif tok[0] == b"f":
            if not 3 <= len(tok) - 1 <= _MAX_POLYGON:
                raise _fail(where, f"line {no}: a face needs 3 to {_MAX_POLYGON} corners, has {len(tok) - 1}")
            face = []
            for t in tok[1:]:
                try:
                    i = int(t.split(b"/", 1)[0])
                except ValueError:
                    raise _fail(
                        where, f"line {no}: corner {sanitize_text(t.decode('latin1'), 30)!r} is not an index"
                    ) from None
                if i == 0:
                    raise _fail(where, f"line {no}: vertex index 0 (OBJ indices start at 1)")
                face.append(i - 1 if i > 0 else len(verts) + i)
            polys.append(face)
    return np.asarray(verts, dtype=np.float64).reshape(-1, 3), _fan(polys)
