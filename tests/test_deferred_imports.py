"""Imports inside functions (docs/architecture.md, "Imports"; issue 35 item 4).

An import sits at the top of its module unless deferring it is measured to matter. Each one inside a
function says why in a comment on its first line or the line above, starting with one of
:data:`REASONS`. What the comment claims is checked here where it can be checked from the source:

- ``start-up:``/``warm-up:`` - the import adds to what importing the module loads. Of our own
  modules: not one that the module already reaches through module-level imports. Of a third-party
  module: not one imported at module level by the module or anything of ours it reaches. (The time in the
  comment was measured when it was written: ``python -X importtime``, or fork after importing the
  module and time the import in the child.)
- ``optional dependency:`` - names a package outside ``[project] dependencies``.
- ``import circle:`` - the imported module reaches this one through module-level imports.
- ``platform:``/``trusted path:`` - a POSIX-only module; a plugin module imported only inside
  :func:`nirspi_pipe.app.plugins.trusted_import_path`.

The checker also runs on a small tree with each kind of violation, to show that it can fail.
"""

from __future__ import annotations

import ast
import re
from dataclasses import dataclass
from pathlib import Path

from test_architecture import SRC, _is_type_checking, _modules, _resolve_from

#: The reasons a function-level import may give (docs/architecture.md).
REASONS = ("start-up:", "warm-up:", "optional dependency:", "import circle:", "platform:", "trusted path:")
#: The import names of ``[project] dependencies`` (pyproject.toml), for ``optional dependency:``.
REQUIRED = {
    "hydra",
    "hydra_plugins",
    "omegaconf",
    "numpy",
    "scipy",
    "pandas",
    "pyarrow",
    "pyopencl",
    "pymeshlab",
    "pyvista",
    "miepython",
    "skimage",
    "matplotlib",
    "threadpoolctl",
    "numba",
}
_REASON = re.compile(r"#\s*(" + "|".join(re.escape(r) for r in REASONS) + r")(.*)$")


@dataclass(frozen=True)
class Deferred:
    module: str
    line: int
    target: str  # the module imported (absolute)
    reason: str  # one of REASONS, or "" when the comment gives none
    text: str


def _package(name: str, path: Path) -> str:
    return name if path.name == "__init__.py" else name.rpartition(".")[0]


def _expand(mod: str) -> set[str]:
    parts = mod.split(".")
    return {".".join(parts[: i + 1]) for i in range(len(parts))}


def _module_level(tree: ast.Module, name: str, path: Path, known: set[str]) -> set[str]:
    """Modules imported when the module is imported (module level, not under TYPE_CHECKING)."""
    out: set[str] = set()

    def visit(stmts: list[ast.stmt]) -> None:
        for node in stmts:
            if isinstance(node, ast.If) and _is_type_checking(node):
                visit(node.orelse)
            elif isinstance(node, ast.Import):
                for alias in node.names:
                    out.update(_expand(alias.name))
            elif isinstance(node, ast.ImportFrom):
                base = _resolve_from(node, _package(name, path))
                out.update(_expand(base))
                out.update(f"{base}.{a.name}" for a in node.names if f"{base}.{a.name}" in known)
            elif isinstance(node, (ast.If, ast.Try, ast.With)):
                for part in ("body", "orelse", "finalbody"):
                    visit(getattr(node, part, []))
                for handler in getattr(node, "handlers", []):
                    visit(handler.body)

    visit(tree.body)
    out.update(_expand(name) - {name})  # importing a.b.c runs a and a.b first
    return out


def _scan(modules: dict[str, Path]) -> tuple[list[Deferred], dict[str, set[str]]]:
    """Every function-level import with its reason, and each module's module-level imports."""
    known = set(modules)
    deferred: list[Deferred] = []
    top: dict[str, set[str]] = {}
    for name, path in modules.items():
        source = path.read_text(encoding="utf-8")
        lines = source.splitlines()
        tree = ast.parse(source)
        top[name] = _module_level(tree, name, path, known)
        for func in ast.walk(tree):
            if not isinstance(func, (ast.FunctionDef, ast.AsyncFunctionDef)):
                continue
            for node in ast.walk(func):
                if isinstance(node, ast.Import):
                    targets = [a.name for a in node.names]
                elif isinstance(node, ast.ImportFrom):
                    base = _resolve_from(node, _package(name, path))
                    subs = [f"{base}.{a.name}" for a in node.names if f"{base}.{a.name}" in known]
                    targets = subs or [base]
                else:
                    continue
                here, above = lines[node.lineno - 1], lines[node.lineno - 2] if node.lineno > 1 else ""
                found = _REASON.search(here) or (_REASON.search(above) if above.strip().startswith("#") else None)
                for target in targets:
                    reason = found.group(1) if found else ""
                    deferred.append(Deferred(name, node.lineno, target, reason, here.strip()))
    return deferred, top


def _reach(top: dict[str, set[str]], start: str) -> set[str]:
    seen: set[str] = set()
    todo = [start]
    while todo:
        for nxt in top.get(todo.pop(), ()):
            if nxt not in seen:
                seen.add(nxt)
                todo.append(nxt)
    return seen


def problems(modules: dict[str, Path]) -> list[str]:
    """Function-level imports whose comment gives no reason, or a reason the source contradicts."""
    deferred, top = _scan(modules)
    out: list[str] = []
    for d in deferred:
        where = f"{d.module}:{d.line}"
        root = d.target.split(".")[0]
        if not d.reason:
            out.append(f"{where}: no reason ({', '.join(REASONS)}): {d.text}")
        elif d.reason in ("start-up:", "warm-up:"):
            reach = _reach(top, d.module) | {d.module}
            if d.target in modules and d.target in reach:
                out.append(f"{where}: {d.target} is loaded with the module anyway; import it at the top")
            if d.target not in modules:
                loaded = set().union(*(top.get(m, set()) for m in reach))
                if d.target in loaded:
                    out.append(f"{where}: {d.target} is imported at module level already; import it at the top")
        elif d.reason == "optional dependency:" and root in REQUIRED:
            out.append(f"{where}: {root} is a required dependency (pyproject.toml), not optional")
        elif d.reason == "import circle:" and d.module not in _reach(top, d.target):
            out.append(f"{where}: {d.target} does not import {d.module}; no circle")
        elif d.reason == "platform:" and root not in {"fcntl", "termios", "resource", "pwd", "grp"}:
            out.append(f"{where}: {root} is not a POSIX-only module")
    return out


def test_every_import_inside_a_function_says_why() -> None:
    found = problems(_modules(SRC))
    assert not found, "\n".join(found)


def test_a_fifth_or_fewer_of_the_imports_are_inside_functions() -> None:
    # 408 of 1395 (29 %) at 3808353; 197 of 1312 (15 %) after issue 35's pass
    deferred, _ = _scan(_modules(SRC))
    total = sum(
        isinstance(n, (ast.Import, ast.ImportFrom))
        for path in _modules(SRC).values()
        for n in ast.walk(ast.parse(path.read_text(encoding="utf-8")))
    )
    inside = len({(d.module, d.line) for d in deferred})
    assert inside / total <= 0.2, f"{inside} of {total} imports are inside functions"


def _tree(tmp_path: Path, files: dict[str, str]) -> dict[str, Path]:
    for rel, text in files.items():
        (tmp_path / rel).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / rel).write_text(text)
    return _modules(tmp_path)


_CLEAN = {
    "pkg/__init__.py": "",
    "pkg/a.py": "import numpy\nfrom pkg import b\n",
    "pkg/b.py": "def f():\n    from pkg import a  # import circle: pkg.a imports this module\n",
    "pkg/c.py": "def f():\n    import matplotlib  # start-up: loads matplotlib (300 ms here)\n",
    "pkg/d.py": "def f():\n    # optional dependency: torch\n    import torch\n",
}
_BROKEN = {
    "untagged": ("pkg/e.py", "def f():\n    import json\n", "no reason"),
    "loaded anyway": ("pkg/e.py", "from pkg import a\ndef f():\n    from pkg import b  # start-up: x\n", "anyway"),
    "third-party at the top": ("pkg/e.py", "import pkg.a\ndef f():\n    import numpy  # start-up: x\n", "already"),
    "a submodule at the top": (
        "pkg/e.py",
        "import scipy.fft\ndef f():\n    import scipy.fft  # start-up: x\n",
        "already",
    ),
    "required, not optional": ("pkg/e.py", "def f():\n    import scipy  # optional dependency: scipy\n", "required"),
    "no circle": ("pkg/e.py", "def f():\n    from pkg import c  # import circle: x\n", "no circle"),
}


def test_the_checker_passes_a_clean_tree(tmp_path: Path) -> None:
    assert problems(_tree(tmp_path, _CLEAN)) == []


def test_the_checker_finds_each_kind_of_violation(tmp_path: Path) -> None:
    for i, (case, (rel, text, expected)) in enumerate(_BROKEN.items()):
        root = tmp_path / str(i)
        found = problems(_tree(root, {**_CLEAN, rel: text}))
        assert len(found) == 1 and expected in found[0], (case, found)
