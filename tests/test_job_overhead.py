"""The per-job and keying shortcuts of issue 42 item 6 give what the slow paths give.

Each shortcut (the sweeper's own resolution of ``${a.b}`` and ``${oc.select:a.b,null}``, the
one-walk JSON conversion, the hash computed once, the cached file checks) is compared with the
code it stands in for, on hard cases drawn by hypothesis.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from omegaconf import OmegaConf

from nirspi_pipe.app.jobcomposer import _NotSimple, _resolve_references

# -- the sweeper's resolution equals OmegaConf's ------------------------------------------------

_KEYS = st.sampled_from(["a", "b", "c", "scene", "distance_mm", "x_1"])
_LEAVES = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(-5, 5),
    st.floats(allow_nan=False, allow_infinity=True, width=32),
    st.sampled_from(["", "text", "???", "a.b", "$", "${", "${ a }"]),
)


def _with_interpolations(paths: list[str]) -> st.SearchStrategy[str]:
    """Interpolation strings naming (mostly) existing paths: references and ``oc.select``."""
    path = st.sampled_from(paths) if paths else _KEYS
    missing = st.sampled_from(["nope", "a.nope", "scene.nope.deeper"])
    target = st.one_of(path, missing)
    return st.one_of(
        target.map(lambda p: "${" + p + "}"),
        target.map(lambda p: "${oc.select:" + p + ",null}"),
        target.map(lambda p: "${oc.select: " + p + " , null}"),
        target.map(lambda p: "${oc.select:" + p + ",3}"),  # another default: OmegaConf's own path
        target.map(lambda p: "x${" + p + "}"),  # string interpolation: OmegaConf's own path
    )


def _paths(node: Any, prefix: str = "") -> list[str]:
    out = []
    if isinstance(node, dict):
        for k, v in node.items():
            p = f"{prefix}.{k}" if prefix else k
            out.append(p)
            out.extend(_paths(v, p))
    return out


@st.composite
def _configs(draw: st.DrawFn) -> dict[str, Any]:
    tree = draw(
        st.recursive(
            _LEAVES,
            lambda inner: st.one_of(st.dictionaries(_KEYS, inner, max_size=4), st.lists(inner, max_size=3)),
            max_leaves=12,
        ).filter(lambda t: isinstance(t, dict))
    )
    paths = _paths(tree)
    interp = _with_interpolations(paths)

    def plant(node: Any) -> Any:
        if isinstance(node, dict):
            return {k: (draw(interp) if draw(st.integers(0, 3)) == 0 else plant(v)) for k, v in node.items()}
        if isinstance(node, list):
            return [plant(v) for v in node]
        return node

    return plant(tree)


def _omegaconf(cfg: dict[str, Any]) -> Any:
    try:
        return ("ok", OmegaConf.to_container(OmegaConf.create(cfg), resolve=True))
    except Exception as exc:  # noqa: BLE001 - compared by kind
        return ("error", type(exc).__name__)


def _same(a: Any, b: Any) -> bool:
    """Equal, NaN-aware, and of the same types (1 and 1.0 and True differ in a job key)."""
    if type(a) is not type(b):
        return False
    if isinstance(a, dict):
        return list(a) == list(b) and all(_same(a[k], b[k]) for k in a)
    if isinstance(a, list):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b, strict=True))
    if isinstance(a, float) and math.isnan(a):
        return math.isnan(b)
    return bool(a == b)


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(_configs())
def test_fast_resolution_is_omegaconfs(cfg: dict[str, Any]) -> None:
    try:
        fast = _resolve_references(json.loads(json.dumps(cfg)))
    except _NotSimple:
        return  # the sweeper hands these to OmegaConf
    kind, slow = _omegaconf(cfg)
    if (kind, slow) == ("error", "InterpolationToMissingValueError"):
        # a plain ``${a}`` whose target is ``???``: the shortcut copies the ``???`` (as before this
        # issue), and the job's stage check then names the key; OmegaConf refuses it here
        assert "???" in json.dumps(fast)
        return
    assert kind == "ok", (cfg, slow)
    assert _same(fast, slow), (cfg, fast, slow)


def test_oc_select_cases_of_the_shipped_configs() -> None:
    base = {"fusion": {"prior_distance_mm": "${oc.select:scene.distance_mm,null}"}}
    for scene in ({"distance_mm": 1000.0}, {"distance_mm": 5}, {}, {"distance_mm": "???"}, {"distance_mm": None}):
        cfg = {"scene": dict(scene), **json.loads(json.dumps(base))}
        assert _same(_resolve_references(cfg), OmegaConf.to_container(OmegaConf.create(cfg), resolve=True))
    # the selected value is itself a reference, resolved in turn
    cfg = {"d": 7.5, "scene": {"distance_mm": "${d}"}, **base}
    assert _resolve_references(cfg)["fusion"]["prior_distance_mm"] == 7.5


def test_unsupported_interpolations_are_left_to_omegaconf() -> None:
    for text in ("${oc.select:scene.distance_mm,3}", "${oc.env:HOME}", "${.a}", "a${b}", "${oc.select:.a,null}"):
        try:
            _resolve_references({"a": 1, "b": 2, "scene": {"distance_mm": 1.0}, "k": text})
        except _NotSimple:
            continue
        raise AssertionError(f"{text} resolved by the shortcut")


# -- jsonable's short path gives what the general one gives -------------------------------------


class _Str(str):
    pass


class _Float(float):
    pass


_JSON_LEAVES = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(-(2**70), 2**70),
    st.floats(allow_nan=True, allow_infinity=True),
    st.text(max_size=4),
    st.builds(np.float64, st.floats(allow_nan=True, allow_infinity=True)),
    st.builds(np.float32, st.floats(width=32, allow_nan=True, allow_infinity=True)),
    st.builds(np.int64, st.integers(-(2**62), 2**62)),
    st.builds(np.bool_, st.booleans()),
    st.builds(_Str, st.text(max_size=3)),
    st.builds(_Float, st.floats(allow_nan=True, allow_infinity=True)),
    st.builds(lambda xs: np.asarray(xs, dtype=np.float64), st.lists(st.floats(), max_size=3)),
)
_JSON_KEYS = st.one_of(
    st.text(max_size=3), st.integers(-3, 3), st.booleans(), st.none(), st.builds(_Str, st.text(max_size=2))
)


def _json_trees() -> st.SearchStrategy[Any]:
    return st.recursive(
        _JSON_LEAVES,
        lambda inner: st.one_of(
            st.dictionaries(_JSON_KEYS, inner, max_size=4),
            st.lists(inner, max_size=4),
            st.lists(inner, max_size=3).map(tuple),
        ),
        max_leaves=20,
    )


@settings(max_examples=300, deadline=None)
@given(_json_trees())
def test_jsonable_short_path_is_the_general_one(value: Any) -> None:
    from nirspi_pipe.strictjson import _jsonable_other, jsonable

    def general(v: Any) -> Any:  # the function before issue 42 item 6: every node by isinstance
        return _jsonable_other_deep(v)

    def _jsonable_other_deep(v: Any) -> Any:
        from collections.abc import Mapping

        if isinstance(v, Mapping):
            return {str(k): _jsonable_other_deep(x) for k, x in v.items()}
        if isinstance(v, (list, tuple)):
            return [_jsonable_other_deep(x) for x in v]
        if isinstance(v, np.ndarray):
            return _jsonable_other_deep(v.tolist())
        return _jsonable_other(v)

    fast, slow = jsonable(value), general(value)
    assert json.dumps(fast, allow_nan=False, sort_keys=True) == json.dumps(slow, allow_nan=False, sort_keys=True)
    assert _same_types(fast, slow)


def _same_types(a: Any, b: Any) -> bool:
    if type(a) is not type(b):
        return False
    if isinstance(a, dict):
        return list(a) == list(b) and all(_same_types(a[k], b[k]) for k in a)
    if isinstance(a, list):
        return len(a) == len(b) and all(_same_types(x, y) for x, y in zip(a, b, strict=True))
    return True


# -- input files: the stat shortcut finds what pathlib finds -----------------------------------


def test_input_files_shortcut_finds_what_pathlib_finds(tmp_path: Path, monkeypatch: Any) -> None:
    from nirspi_pipe import jobkey

    (tmp_path / "rec.npz").write_bytes(b"x")
    (tmp_path / "dir").mkdir()
    (tmp_path / "dir" / "w.json").write_text("{}")
    (tmp_path / "link.npz").symlink_to(tmp_path / "rec.npz")
    (tmp_path / "dangling").symlink_to(tmp_path / "nope")
    (tmp_path / "home").mkdir()
    (tmp_path / "home" / "h.txt").write_text("h")
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    texts = [
        "rec.npz", "./rec.npz", "dir//w.json", "dir/./w.json", "dir/../rec.npz", "rec.npz/", "rec.npz/.",
        "dir", "dir/", ".", "..", "link.npz", "dangling", "nope", "~/h.txt", "~", str(tmp_path / "rec.npz"),
        str(tmp_path) + "//dir/w.json", "rec.npz/x", "a" * 300, "spiral", "nirspi_pipe.scene.objects.Sphere",
    ]  # fmt: skip
    config = {
        "a": {str(i): t for i, t in enumerate(texts)},
        "l": [texts[0], {"k": texts[2]}],
        "hydra": {"x": "rec.npz"},
    }

    def by_pathlib(cfg: Any, base: Path) -> dict[str, Path]:
        monkeypatch.setattr(jobkey, "_POSIX", False)  # the shortcut off: pathlib alone
        try:
            return jobkey.input_files(cfg, base)
        finally:
            monkeypatch.setattr(jobkey, "_POSIX", True)

    fast = jobkey.input_files(config, tmp_path)
    assert fast == by_pathlib(config, tmp_path)
    assert {"a.0", "a.1", "a.2", "a.3", "a.4", "a.5", "a.6", "a.11", "a.14", "a.16", "a.17", "l[0]", "l[1].k"} == set(
        fast
    )


# -- the record's keys, computed once, are the keys --------------------------------------------


def test_new_record_keys_equal_the_job_keys(tmp_path: Path, monkeypatch: Any) -> None:
    from nirspi_pipe.jobkey import InputHasher, config_hash, job_key_of
    from nirspi_pipe.records import new_record

    monkeypatch.chdir(tmp_path)
    (tmp_path / "rec.npz").write_bytes(b"abc")
    for config in ({"a": 1, "b": [1.5, math.inf]}, {"a": 1, "recording": "rec.npz"}, {"objective": ["x"], "a": 2}):
        meta = new_record(config, {}, [], 0, 1)["meta"]
        assert meta["config_hash"] == config_hash(config)
        assert meta["job_key"] == job_key_of(config, InputHasher().hashes(config))
    assert job_key_of({"a": 1}, {}, "given") == "given"  # the hash handed over is used as it is


# -- attempts-style bookkeeping can skip the fsync; records keep it ------------------------------


def test_atomic_write_fsyncs_unless_told_not_to(tmp_path: Path, monkeypatch: Any) -> None:
    import os

    from nirspi_pipe import outputfiles
    from nirspi_pipe.records import write_record

    calls: list[int] = []
    real = os.fsync
    monkeypatch.setattr(outputfiles.os, "fsync", lambda fd: (calls.append(fd), real(fd))[1])
    outputfiles.atomic_write(tmp_path / "a.json", "{}", durable=False)
    assert calls == [] and (tmp_path / "a.json").read_text() == "{}"
    outputfiles.atomic_write(tmp_path / "b.json", "{}")
    assert len(calls) == 1
    write_record(tmp_path, {"meta": {}})
    assert len(calls) == 2  # record.json stays durable
    assert not [p for p in tmp_path.iterdir() if p.name.endswith(".tmp")]


def test_the_attempts_count_is_written_without_a_flush(tmp_path: Path, monkeypatch: Any) -> None:
    """attempts.json is bookkeeping (lost: one more try at worst): no fsync in the sweeping
    process's claim of a job, and the count still goes up."""
    import os

    from nirspi_pipe import outputfiles
    from nirspi_pipe.app import jobs

    calls: list[int] = []
    real = os.fsync
    monkeypatch.setattr(outputfiles.os, "fsync", lambda fd: (calls.append(fd), real(fd))[1])
    assert jobs._bump_attempts(tmp_path) == 1
    assert jobs._bump_attempts(tmp_path) == 2
    assert calls == [] and jobs.attempts_with_this_code(tmp_path) == 2


# -- set_plain copies on write: the sweeper's base is never changed -----------------------------


def _old_set_plain(cfg: dict[str, Any], dotted: str, value: Any) -> bool:
    """set_plain before issue 42 item 6 (on a deep copy of the base)."""
    node: Any = cfg
    *parents, leaf = dotted.split(".")
    for part in parents:
        if not isinstance(node, dict) or part not in node:
            return False
        node = node[part]
    if not isinstance(node, dict) or leaf not in node or isinstance(node[leaf], dict) or isinstance(value, dict):
        return False
    node[leaf] = value
    return True


_PLAIN_TREES = st.recursive(
    st.one_of(st.none(), st.integers(-3, 3), st.text(max_size=2)),
    lambda inner: st.one_of(st.dictionaries(_KEYS, inner, max_size=3), st.lists(inner, max_size=2)),
    max_leaves=10,
).filter(lambda t: isinstance(t, dict))


@settings(max_examples=200, deadline=None)
@given(_PLAIN_TREES, st.data())
def test_set_plain_copies_on_write(base: dict[str, Any], data: st.DataObject) -> None:
    import copy

    from nirspi_pipe.app.jobcomposer import set_plain

    paths = _paths(base) + ["nope", "a.nope.x"]  # existing keys at any depth, and absent ones
    values = st.one_of(st.integers(), st.lists(st.integers(), max_size=2), st.just({"x": 1}))
    updates = data.draw(st.lists(st.tuples(st.sampled_from(paths), values), max_size=4))
    before = copy.deepcopy(base)
    new, old = dict(base), copy.deepcopy(base)
    for dotted, value in updates:
        ok_old = _old_set_plain(old, dotted, value)
        assert set_plain(new, dotted, value) == ok_old
        if not ok_old:
            break  # the sweeper composes this job in full
    else:
        assert new == old
    assert base == before  # the base the next job starts from is untouched


def test_new_record_reads_an_input_file_once_until_it_changes(tmp_path: Path, monkeypatch: Any) -> None:
    import os

    from nirspi_pipe import records

    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(records, "_INPUTS", records.InputHasher())
    rec = tmp_path / "rec.npz"
    rec.write_bytes(b"abc" * 1000)
    config = {"source": {"path": "rec.npz"}}
    first = records.new_record(config, {}, [], 0, 1)["meta"]
    again = records.new_record(config, {}, [], 1, 1)["meta"]
    assert records._INPUTS.bytes_read == 3000  # read once for both jobs
    assert first["inputs"] == again["inputs"] and first["job_key"] == again["job_key"]
    rec.write_bytes(b"abd" * 1000)  # same size, new content
    st = rec.stat()
    os.utime(rec, ns=(st.st_atime_ns, st.st_mtime_ns + 1_000_000))  # a new mtime, as a later write has
    changed = records.new_record(config, {}, [], 2, 1)["meta"]
    assert records._INPUTS.bytes_read == 6000
    assert changed["inputs"] != first["inputs"] and changed["job_key"] != first["job_key"]
    monkeypatch.setenv("NIRSPI_READ_BUDGET_MB", "0.001")  # 1048 bytes: the process-wide cache asks again
    assert records.new_record(config, {}, [], 3, 1)["meta"]["inputs"]["source.path"].startswith("not hashed: 3000")
