"""Structural rules of the code base, by an AST scan of everything under ``src/``
(``nirspi_pipe`` and ``hydra_plugins``) and of the folders ``pyproject.toml`` maps into the
package (``conf/`` is ``nirspi_pipe.conf``, ``experiments/`` is ``nirspi_pipe.experiments``),
imports inside functions included:

- two layers with one direction: the runner (every module of ``nirspi_pipe`` outside
  ``nirspi_pipe.app``: stages, ``instantiate``, ``pipeline``, ``execute``, ``records``, tables)
  imports nothing of Hydra, OmegaConf or the app, not even transitively; the app
  (``nirspi_pipe.app``: command line, validation, configs, sweeper, launcher, jobs, plugins,
  Python API), the config groups ``nirspi_pipe.conf`` (importing them registers the schemas
  through ``app.configs``) and ``hydra_plugins`` sit above it;
- no import circle anywhere under ``src/``;
- no private Hydra API.

What counts as reaching a module: every ``import``/``from … import`` (at module level or inside
a function); importing ``a.b.c`` runs the ``__init__`` of ``a`` and ``a.b`` first, so a module
reaches its parent packages; a name a package serves lazily (PEP 562: a module-level
``__getattr__``, as ``nirspi_pipe.run`` is served from ``nirspi_pipe.app.api``) reaches what that
``__getattr__`` imports, whether it is taken with ``from nirspi_pipe import run`` or read as the
attribute ``nirspi_pipe.run`` of an imported package (or ``getattr(nirspi_pipe, "run")``); an
import by a string (``importlib.import_module``, ``__import__``, ``runpy.run_module``,
``pkgutil.resolve_name``; a name built from literals, or known only by its start as in
``f"pkg.{name}"``, which reaches every module below ``pkg``); code given to ``exec``, ``eval`` or
``compile`` as a literal. Imports under ``if TYPE_CHECKING:``
(anywhere, and in the ``else:`` of ``if not TYPE_CHECKING:``) do not run, so they are no edge of
the reach; a runner module may still not name the app there. The other branch runs: it is an edge.
What this scan cannot see (a name computed at run time) the run-time test covers:
tests/test_layering_runtime.py runs jobs with Hydra, OmegaConf and the app blocked from import.

The rules are checked on the real tree and, to show that they can fail, on small packages
written into a temporary folder (the circle of 2191b36: ``cli`` ↔ ``launcher``; the three holes
an outside review found in the previous version of this test, and the lazy re-export).
"""

from __future__ import annotations

import ast
import re
import sys
import textwrap
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SRC = ROOT / "src"
APP = "nirspi_pipe.app"
#: Above the runner besides ``nirspi_pipe.app``: the config groups (``conf/__init__.py``
#: imports ``app.configs``) and the Hydra plugin package.
APP_SIDE = (APP, "nirspi_pipe.conf", "hydra_plugins")
CONFIG_SYSTEM = ("hydra", "omegaconf")
#: The top-level facade: ``nirspi_pipe.run`` etc. are PEP 562 lazy re-exports of
#: :mod:`nirspi_pipe.app.api`, imported on first attribute access only, never by a runner module.
FACADE = "nirspi_pipe"
#: Command-line tools and scripts above both layers (they compose configs to time or check the runner).
TOOLS = (
    "nirspi_pipe.benchmarks",
    "nirspi_pipe.bench",
    "nirspi_pipe.readme_numbers",
    "nirspi_pipe.hardcases",
    "nirspi_pipe.reproduce",
    "nirspi_pipe.experiments",
)
STAGE_PACKAGES = ("sources", "solvers", "sfs", "mesh", "itof", "physics", "scene", "patterns", "upscale", "device")
#: Modules outside the private-API rule for now (owned elsewhere; see the report of issue 10).
PRIVATE_HYDRA_EXEMPT: set[str] = set()


def _mapped_packages() -> dict[str, Path]:
    """``{package: folder}`` of the folders outside ``src/`` that ``pyproject.toml`` maps into the package."""
    line = re.search(r"^package-dir = \{(.*)\}$", (ROOT / "pyproject.toml").read_text(), re.M)
    assert line, "pyproject.toml: no package-dir line"  # one line of "package" = "folder" pairs (tomllib is 3.11+)
    return {pkg: ROOT / folder for pkg, folder in re.findall(r'"([^"]*)" = "([^"]*)"', line.group(1)) if pkg}


def _module_name(path: Path, root: Path, prefix: str = "") -> str:
    parts = list(path.relative_to(root).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(([prefix] if prefix else []) + parts)


@dataclass
class _Scan:
    """What one module imports and reads, from its AST."""

    imports: list[tuple[str, int]] = field(default_factory=list)  # run at import or call time
    typing: list[tuple[str, int]] = field(default_factory=list)  # under ``if TYPE_CHECKING:``
    lazy: list[str] = field(default_factory=list)  # imported by a module-level ``__getattr__``
    bound: set[str] = field(default_factory=set)  # names bound at module level
    has_getattr: bool = False


def _is_type_checking(node: ast.If) -> bool:
    t = node.test
    return (isinstance(t, ast.Name) and t.id == "TYPE_CHECKING") or (
        isinstance(t, ast.Attribute) and t.attr == "TYPE_CHECKING"
    )


def _typing_only(node: ast.If) -> list[ast.stmt]:
    """The statements of an ``if`` that run only under a type checker: the body of
    ``if TYPE_CHECKING:``, the ``else:`` of ``if not TYPE_CHECKING:``. The other branch runs."""
    if _is_type_checking(node):
        return node.body
    t = node.test
    if isinstance(t, ast.UnaryOp) and isinstance(t.op, ast.Not) and _is_type_checking(ast.If(test=t.operand)):
        return node.orelse
    return []


#: Calls that import the module their first argument names (``importlib.import_module("a.b")``,
#: ``__import__("a.b")``, ``runpy.run_module("a.b")``, ``pkgutil.resolve_name("a.b:c")``), by the
#: dotted name the call's function is bound to.
STRING_IMPORTS = (
    "importlib.import_module",
    "__import__",
    "builtins.__import__",
    "importlib.__import__",
    "runpy.run_module",
    "pkgutil.resolve_name",
)


def _const_str(node: ast.AST | None) -> str | None:
    """The string an expression always evaluates to (a literal, ``"a." + "b"``, an f-string
    without fields), or None."""
    if isinstance(node, ast.Constant) and isinstance(node.value, str):
        return node.value
    if isinstance(node, ast.BinOp) and isinstance(node.op, ast.Add):
        left, right = _const_str(node.left), _const_str(node.right)
        return left + right if left is not None and right is not None else None
    if isinstance(node, ast.JoinedStr):
        parts = [_const_str(v) for v in node.values]
        return "".join(p for p in parts if p is not None) if all(p is not None for p in parts) else None
    return None


def _bound_to(node: ast.expr, aliases: dict[str, str]) -> str | None:
    """The dotted name an expression such as ``importlib.import_module`` or ``import_module``
    refers to, through the module's imports (a builtin keeps its own name)."""
    chain: list[str] = []
    while isinstance(node, ast.Attribute):
        chain.append(node.attr)
        node = node.value
    if not isinstance(node, ast.Name):
        return None
    return ".".join([aliases.get(node.id, node.id), *reversed(chain)])


def _const_prefix(node: ast.AST | None) -> str:
    """The constant start of a string expression (``f"a.b.{x}"`` → ``a.b.``), or ``""``."""
    if isinstance(node, ast.BinOp) and isinstance(node.op, ast.Add):
        left = _const_str(node.left)
        return left + _const_prefix(node.right) if left is not None else _const_prefix(node.left)
    if isinstance(node, ast.JoinedStr):
        out = ""
        for v in node.values:
            part = _const_str(v)
            if part is None:
                break
            out += part
        return out
    return ""


def _string_import(call: ast.Call, aliases: dict[str, str], package: str) -> list[str]:
    """What a call imports by a string: ``importlib.import_module("a.b")`` (relative names with a
    constant ``package``), ``__import__("a.b", fromlist=["c"])`` (``a.b`` and ``a.b.c``). A name
    known only by its start (``f"a.b.{x}"``) is the pattern ``a.b.*``: any module below ``a.b``."""
    if _bound_to(call.func, aliases) not in STRING_IMPORTS:
        return []
    kw = {k.arg: k.value for k in call.keywords if k.arg}
    arg = call.args[0] if call.args else kw.get("name", kw.get("mod_name"))
    name = _const_str(arg)
    name = name.replace(":", ".") if name is not None else None  # pkgutil.resolve_name("a.b:c")
    if name is None:
        prefix = _const_prefix(arg)
        return [prefix.rstrip(".") + ".*"] if "." in prefix and not prefix.startswith(".") else []
    if not name:
        return []
    if name.startswith("."):  # import_module(".x", package="a.b")
        base = _const_str(call.args[1] if len(call.args) > 1 else kw.get("package")) or package
        dots = len(name) - len(name.lstrip("."))
        parts = base.split(".")
        name = ".".join(parts[: len(parts) - dots + 1] + [name.lstrip(".")])
    found = [name]
    fromlist = call.args[3] if len(call.args) > 3 else kw.get("fromlist")
    if isinstance(fromlist, (ast.List, ast.Tuple)):
        found += [f"{name}.{n}" for n in (_const_str(e) for e in fromlist.elts) if n]
    return found


def _resolve_from(node: ast.ImportFrom, package: str) -> str:
    if not node.level:
        return node.module or ""
    base = package.split(".")
    base = base[: len(base) - node.level + 1]
    return ".".join(base + ([node.module] if node.module else []))


def _scan(path: Path, name: str, text: str | None = None) -> _Scan:
    """Imports of ``path`` (module ``name``), absolute, with line numbers; function-level too.
    ``import a.b`` binds ``a``, so a later attribute read ``a.x.y`` counts as a use of ``a.x.y``
    (reported with the imports: ``from a import x`` and ``a.x`` reach the same things). Code
    given to ``exec``/``eval``/``compile`` as a literal is scanned as part of the module (``text``:
    such code, scanned in the module's package)."""
    tree = ast.parse(path.read_text() if text is None else text, filename=str(path))
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    scan = _Scan()
    aliases: dict[str, str] = {}  # local name -> the module (or module.attribute) it is bound to
    typing_nodes: set[int] = set()
    lazy_nodes: set[int] = set()
    for node in ast.walk(tree):  # ``if TYPE_CHECKING:`` anywhere; its ``else:`` runs
        if isinstance(node, ast.If):
            typing_nodes |= {id(n) for stmt in _typing_only(node) for n in ast.walk(stmt)}
    for top in tree.body:
        if isinstance(top, ast.If) and _is_type_checking(top):
            pass  # its names are bound only for a type checker
        elif isinstance(top, ast.FunctionDef) and top.name == "__getattr__":
            scan.has_getattr = True
            lazy_nodes |= {id(n) for n in ast.walk(top)}
            scan.bound.add(top.name)
        elif isinstance(top, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            scan.bound.add(top.name)
        elif isinstance(top, (ast.Assign, ast.AnnAssign, ast.AugAssign)):
            targets = top.targets if isinstance(top, ast.Assign) else [top.target]
            scan.bound |= {n.id for t in targets for n in ast.walk(t) if isinstance(n, ast.Name)}
    for node in ast.walk(tree):
        found: list[str] = []
        if not isinstance(node, (ast.Import, ast.ImportFrom)):
            continue
        if isinstance(node, ast.Import):
            for a in node.names:
                found.append(a.name)
                local = a.asname or a.name.split(".")[0]
                aliases[local] = a.name if a.asname else local
        elif isinstance(node, ast.ImportFrom):
            mod = _resolve_from(node, package)
            found.append(mod)
            for a in node.names:
                found.append(f"{mod}.{a.name}")
                aliases[a.asname or a.name] = f"{mod}.{a.name}"
        if not found:
            continue
        if id(node) in lazy_nodes:
            scan.lazy += found
        elif id(node) in typing_nodes:
            scan.typing += [(m, node.lineno) for m in found]
        else:
            scan.imports += [(m, node.lineno) for m in found]
            if node in tree.body:  # module level: the names it binds
                scan.bound |= {a.asname or a.name.split(".")[0] for a in node.names}

    def note(dotted: list[str], node: ast.expr) -> None:
        if id(node) in lazy_nodes:
            scan.lazy += dotted
        elif id(node) in typing_nodes:
            scan.typing += [(m, node.lineno) for m in dotted]
        else:
            scan.imports += [(m, node.lineno) for m in dotted]

    # attribute reads on an imported name: ``nirspi_pipe.run`` after ``import nirspi_pipe``, also
    # as ``getattr(nirspi_pipe, "run")``; imports by a string (``importlib.import_module("a.b")``,
    # ``__import__("a.b")``), and ``getattr`` on what such a call returns
    for node in ast.walk(tree):
        if isinstance(node, ast.Attribute) and isinstance(node.ctx, ast.Load):
            chain: list[str] = []
            inner: ast.expr = node
            while isinstance(inner, ast.Attribute):
                chain.append(inner.attr)
                inner = inner.value
            if isinstance(inner, ast.Name) and inner.id in aliases:
                note([".".join([aliases[inner.id], *reversed(chain)])], node)
        elif isinstance(node, ast.Call):
            note(_string_import(node, aliases, package), node)
            code = _const_str(node.args[0]) if node.args else None
            if isinstance(node.func, ast.Name) and node.func.id in ("exec", "eval", "compile") and code:
                try:
                    inner_scan = _scan(path, name, textwrap.dedent(code))
                except SyntaxError:
                    inner_scan = _Scan()
                note([m for m, _ in inner_scan.imports + inner_scan.typing], node)
            if isinstance(node.func, ast.Name) and node.func.id == "getattr" and len(node.args) >= 2:
                attr, obj = _const_str(node.args[1]), node.args[0]
                if isinstance(obj, ast.Call):
                    base = (_string_import(obj, aliases, package) or [None])[0]
                else:
                    base = aliases.get(obj.id) if isinstance(obj, ast.Name) else None
                if base and attr:
                    note([f"{base}.{attr}"], node)
    return scan


def _imports(path: Path, root: Path = SRC) -> list[tuple[str, int]]:
    """Every module ``path`` imports (absolute names), with line numbers; function-level too."""
    return _scan(path, _module_name(path, root)).imports


def _modules(root: Path, mapped: dict[str, Path] | None = None) -> dict[str, Path]:
    """``{module: file}`` under ``root``, plus the mapped folders (``{package: folder}``)."""
    out = {_module_name(p, root): p for p in root.rglob("*.py")}
    for pkg, folder in (mapped or {}).items():
        out |= {_module_name(p, folder, pkg): p for p in folder.rglob("*.py")}
    return out


def _owner(mod: str, modules: dict[str, Path]) -> str:
    """The deepest of ``a.b.c`` / ``a.b`` / ``a`` that is one of our modules ('' if none)."""
    while mod and mod not in modules:
        mod = mod.rpartition(".")[0]
    return mod


def _graph(root: Path, mapped: dict[str, Path] | None = None, *, reach: bool = True) -> dict[str, set[str]]:
    """``{module: modules it imports}`` over ``root`` (and the mapped folders); a third-party
    import is a node named by its top-level package (``hydra``), so that transitive reach sees it.

    ``reach=True`` (the layer rule): a module also reaches its parent packages (their
    ``__init__`` runs first), and a lazily served name reaches what the package's ``__getattr__``
    imports; ``if TYPE_CHECKING:`` imports are left out. ``reach=False`` (the circle rule): the
    edges of the code's own ``import`` statements, ``TYPE_CHECKING`` ones included, without the
    parent packages (a package's ``__init__`` runs before any of its modules anyway)."""
    modules = _modules(root, mapped)
    scans = {name: _scan(path, name) for name, path in modules.items()}

    def lazy_targets(mod: str) -> set[str]:
        """What reading ``mod`` (``pkg.name``) runs when ``pkg`` serves ``name`` lazily."""
        owner = _owner(mod, modules)
        rest = mod[len(owner) + 1 :].split(".")[0] if owner and mod != owner else ""
        s = scans.get(owner)
        if not rest or s is None or not s.has_getattr or rest in s.bound or f"{owner}.{rest}" in modules:
            return set()
        return {m for m in s.lazy if m.split(".")[0] in CONFIG_SYSTEM or _owner(m, modules)}

    def expand(mod: str) -> set[str]:
        """``a.b.*`` (a string import known by its start): ``a.b`` and every module below it."""
        if not mod.endswith(".*"):
            return {mod}
        base = mod[:-2]
        return {base} | {m for m in modules if m.startswith(base + ".")}

    graph: dict[str, set[str]] = {name: set() for name in modules}
    for name, s in scans.items():
        edges = list(s.imports) + ([] if reach else list(s.typing))
        for mod, _ in edges:
            for target in expand(mod) | lazy_targets(mod):
                top = target.split(".")[0]
                if top in CONFIG_SYSTEM:
                    graph[name].add(top)
                    graph.setdefault(top, set())
                    continue
                owner = _owner(target, modules)
                if owner and owner != name and (reach or not name.startswith(owner + ".")):
                    graph[name].add(owner)
        if reach:
            parts = name.split(".")
            graph[name] |= {p for i in range(1, len(parts)) if (p := ".".join(parts[:i])) in modules}
    return graph


def _circles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components of more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    cycles: list[list[str]] = []
    counter = [0]

    def strongconnect(v: str) -> None:
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph.get(v, ())):
            if w not in index:
                strongconnect(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                cycles.append(sorted(comp))

    sys.setrecursionlimit(max(sys.getrecursionlimit(), 10000))
    for v in sorted(graph):
        if v not in index:
            strongconnect(v)
    return cycles


def _is_app(name: str) -> bool:
    return any(name == a or name.startswith(a + ".") for a in APP_SIDE)


def _is_runner(name: str) -> bool:
    return (
        name.split(".")[0] == "nirspi_pipe"
        and name != FACADE
        and not _is_app(name)
        and not any(name == t or name.startswith(t + ".") for t in TOOLS)
    )


def _layer_violations(graph: dict[str, set[str]]) -> list[str]:
    """Each runner module that reaches Hydra, OmegaConf or the app, with the shortest chain of
    imports (breadth first) to the first such module."""
    bad = []
    for start in sorted(n for n in graph if _is_runner(n)):
        parent: dict[str, str | None] = {start: None}
        todo = deque([start])
        hit = None
        while todo and hit is None:
            v = todo.popleft()
            for w in sorted(graph.get(v, ())):
                if w not in parent:
                    parent[w] = v
                    todo.append(w)
                    if w in CONFIG_SYSTEM or _is_app(w):
                        hit = w
                        break
        if hit is not None:
            chain = [hit]
            while parent[chain[-1]] is not None:
                chain.append(parent[chain[-1]])  # type: ignore[arg-type]
            bad.append(" -> ".join(reversed(chain)))
    return bad


def _typing_violations(root: Path, mapped: dict[str, Path] | None = None) -> list[str]:
    """Runner modules that name the app or the config system under ``if TYPE_CHECKING:``."""
    return [
        f"{name}:{line} imports {mod}"
        for name, path in sorted(_modules(root, mapped).items())
        if _is_runner(name)
        for mod, line in _scan(path, name).typing
        if mod.split(".")[0] in CONFIG_SYSTEM or _is_app(mod)
    ]


MAPPED = _mapped_packages()
MODULES = _modules(SRC, MAPPED)


def test_the_runner_reaches_nothing_of_hydra() -> None:
    bad = _layer_violations(_graph(SRC, MAPPED)) + _typing_violations(SRC, MAPPED)
    assert not bad, "the runner must not import Hydra, OmegaConf or nirspi_pipe.app: " + "; ".join(bad)


def _named_upper_layers(root: Path, mapped: dict[str, Path] | None = None) -> list[str]:
    """Runner modules whose strings (docstrings aside) name a module or class of a layer above
    the runner (``"nirspi_pipe.app.results.CollectResults"`` in an allow-list, ``"hydra.utils.x"``
    handed to a locator): the runner names nothing of them, so it cannot come to build one."""
    upper = "|".join(re.escape(m) for m in (*CONFIG_SYSTEM, *APP_SIDE, *TOOLS))
    pattern = re.compile(rf"(?<![\w.])({upper})\.(\w|$)")  # "$": the start of f"omegaconf.{name}"
    bad = []
    for name, path in sorted(_modules(root, mapped).items()):
        if not _is_runner(name):
            continue
        tree = ast.parse(path.read_text())
        docs = {
            id(n.body[0].value)
            for n in ast.walk(tree)
            if isinstance(n, (ast.Module, ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef))
            and n.body
            and isinstance(n.body[0], ast.Expr)
            and isinstance(n.body[0].value, ast.Constant)
        }
        bad += [
            f"{name}:{n.lineno} names {m.group(0)}…"
            for n in ast.walk(tree)
            if isinstance(n, ast.Constant) and isinstance(n.value, str) and id(n) not in docs
            for m in [pattern.search(n.value)]
            if m
        ]
    return bad


def test_the_runner_names_nothing_above_it() -> None:
    bad = _named_upper_layers(SRC, MAPPED)
    assert not bad, "the runner must name no class of Hydra, OmegaConf or the app (issue 42): " + "; ".join(bad)


def test_a_runner_string_naming_the_app_is_found(tmp_path: Path) -> None:
    src, mapped = _facade_tree(
        tmp_path,
        {
            "nirspi_pipe/records.py": '"""Built by nirspi_pipe.app.results.CollectResults (a docstring)."""\n'
            'ALLOWED = {"nirspi_pipe.app.results.CollectResults", "nirspi_pipe.stats.X"}\n',
            "nirspi_pipe/stats.py": "def f(x):\n    return f'omegaconf.{x}'\n",
        },
    )
    bad = _named_upper_layers(src, mapped)
    assert [b.split(" ")[0] for b in bad] == ["nirspi_pipe.records:2", "nirspi_pipe.stats:2"], bad


def test_no_import_circles_under_src() -> None:
    circles = _circles(_graph(SRC, MAPPED, reach=False))
    assert not circles, f"import circles: {circles}"


@pytest.mark.parametrize("package", STAGE_PACKAGES)
def test_no_stage_imports_hydra_or_omegaconf(package: str) -> None:
    bad = [
        f"{p.relative_to(SRC)}:{line} imports {mod}"
        for p in (SRC / "nirspi_pipe" / package).rglob("*.py")
        for mod, line in _imports(p)
        if mod.split(".")[0] in CONFIG_SYSTEM or _is_app(mod)
    ]
    assert not bad, "stages must not know the config system: " + "; ".join(bad)


def test_no_private_hydra_api() -> None:
    bad = [
        f"{name}:{line} imports {mod}"
        for name, p in MODULES.items()
        if name not in PRIVATE_HYDRA_EXEMPT
        for mod, line in _scan(p, name).imports
        if mod.startswith("hydra._internal")
    ]
    assert not bad, "; ".join(bad)


def test_the_scan_covers_both_packages_and_function_level_imports() -> None:
    assert len(MODULES) > 50
    assert "hydra_plugins.nirspi_pipe_sweeper" in MODULES
    graph = _graph(SRC, MAPPED)
    # conf/ is scanned as the package it is installed as, on the app's side
    assert "nirspi_pipe.app.configs" in graph["nirspi_pipe.conf"] and _is_app("nirspi_pipe.conf")
    # every module reaches its parent packages; the facade's lazy names reach the API
    assert "nirspi_pipe" in graph["nirspi_pipe.records"]
    assert "nirspi_pipe.app.api" in _scan(MODULES["nirspi_pipe"], "nirspi_pipe").lazy
    # hydra_plugins is scanned: it imports the app's sweeper and launcher
    assert {"nirspi_pipe.app.launcher", "nirspi_pipe.app.sweeper"} <= graph["hydra_plugins.nirspi_pipe_sweeper"]
    # function-level imports count: api.py imports Hydra only inside functions
    assert "hydra" in graph["nirspi_pipe.app.api"]
    assert "nirspi_pipe.physics.effects" in graph["nirspi_pipe.sources.simulator"]
    runner = [n for n in graph if _is_runner(n)]
    for name in ("nirspi_pipe.pipeline", "nirspi_pipe.instantiate", "nirspi_pipe.execute", "nirspi_pipe.records"):
        assert name in runner
    assert not any(_is_runner(n) for n in ("nirspi_pipe.app.cli", "hydra_plugins.nirspi_pipe_sweeper"))


# ---- the rules can fail: small packages with the faults the rules are for --------------------


def _write_tree(root: Path, files: dict[str, str]) -> Path:
    for rel, text in files.items():
        path = root / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)
    return root


def test_the_circle_of_2191b36_is_found(tmp_path: Path) -> None:
    """2191b36's circle: ``launcher`` imported ``cli.execute_job`` inside a function, and ``cli``
    reached the launcher through ``sweeper`` → ``hydra_plugins`` (reduced to its five files)."""
    root = _write_tree(
        tmp_path,
        {
            "nirspi_pipe/__init__.py": "",
            "nirspi_pipe/cli.py": "def run():\n    from nirspi_pipe.sweeper import register_hydra_plugins\n",
            "nirspi_pipe/sweeper.py": "def register_hydra_plugins():\n    from hydra_plugins.nirspi_pipe_sweeper import X\n",
            "nirspi_pipe/launcher.py": "def _execute():\n    from nirspi_pipe.cli import execute_job\n",
            "nirspi_pipe/results.py": "from nirspi_pipe.sweeper import load_sweep_file\n",
            "hydra_plugins/nirspi_pipe_sweeper/__init__.py": "from nirspi_pipe.launcher import L\n",
        },
    )
    circles = _circles(_graph(root))
    assert circles == [
        ["hydra_plugins.nirspi_pipe_sweeper", "nirspi_pipe.cli", "nirspi_pipe.launcher", "nirspi_pipe.sweeper"]
    ]


def test_a_transitive_reach_of_hydra_is_found(tmp_path: Path) -> None:
    """2191b36's emulator reached Hydra through ``configs``; the runner reaching the app is
    refused too, however many modules lie between."""
    root = _write_tree(
        tmp_path,
        {
            "nirspi_pipe/__init__.py": "",
            "nirspi_pipe/device/__init__.py": "",
            "nirspi_pipe/device/emulator.py": "def main():\n    from nirspi_pipe.configs import render_scene\n",
            "nirspi_pipe/configs.py": "from hydra import compose\n",
            "nirspi_pipe/pipeline.py": "import nirspi_pipe.records\n",
            "nirspi_pipe/records.py": "def f():\n    from nirspi_pipe.app.cli import x\n",
            "nirspi_pipe/app/__init__.py": "",
            "nirspi_pipe/app/cli.py": "import omegaconf\n",
            "nirspi_pipe/tables.py": "import numpy\n",
        },
    )
    bad = _layer_violations(_graph(root))
    assert "nirspi_pipe.device.emulator -> nirspi_pipe.configs -> hydra" in bad
    assert "nirspi_pipe.pipeline -> nirspi_pipe.records -> nirspi_pipe.app.cli" in bad
    assert not any(b.startswith("nirspi_pipe.tables") for b in bad)


#: The facade as it is: PEP 562 lazy names served from ``app.api``, the types under TYPE_CHECKING.
_FACADE = (
    "from typing import TYPE_CHECKING\n"
    "__version__ = '0'\n"
    "if TYPE_CHECKING:\n    from nirspi_pipe.app.api import run\n"
    "def __getattr__(name):\n    from nirspi_pipe.app import api\n    return getattr(api, name)\n"
)
_HOLES = {
    "from-facade": ("nirspi_pipe/records.py", "from nirspi_pipe import run\n"),
    "facade-attribute": ("nirspi_pipe/pipeline.py", "import nirspi_pipe\n\ndef go():\n    nirspi_pipe.run([])\n"),
    "facade-attribute-as": ("nirspi_pipe/pipeline.py", "import nirspi_pipe as nip\n\ndef go():\n    nip.run([])\n"),
    "submodule-then-facade": ("nirspi_pipe/pipeline.py", "import nirspi_pipe.records\nnirspi_pipe.run\n"),
    "mapped-conf": ("nirspi_pipe/stats.py", "def f():\n    import nirspi_pipe.conf\n"),
    "typing-only": (
        "nirspi_pipe/stats.py",
        "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from nirspi_pipe.app.api import RunResult\n",
    ),
}


def _facade_tree(root: Path, extra: dict[str, str], facade: str = _FACADE) -> tuple[Path, dict[str, Path]]:
    """A small tree: the facade, three runner modules, the app's API and configs, and a ``conf``
    folder outside ``src/`` mapped into the package that imports ``app.configs``."""
    files = {
        "src/nirspi_pipe/__init__.py": facade,
        "src/nirspi_pipe/records.py": "import json\n",
        "src/nirspi_pipe/pipeline.py": "from nirspi_pipe import records\nimport nirspi_pipe.records as r\n",
        "src/nirspi_pipe/stats.py": "import numpy\nfrom nirspi_pipe import __version__\n",
        "src/nirspi_pipe/app/__init__.py": "",
        "src/nirspi_pipe/app/api.py": "from nirspi_pipe.pipeline import records\ndef run(o):\n    import hydra\n",
        "src/nirspi_pipe/app/configs.py": "import hydra\n",
        "conf/__init__.py": "from nirspi_pipe.app.configs import register_schemas\n",
    }
    _write_tree(root, {**files, **{f"src/{k}": v for k, v in extra.items()}})
    return root / "src", {"nirspi_pipe.conf": root / "conf"}


def test_the_clean_facade_tree_passes(tmp_path: Path) -> None:
    src, mapped = _facade_tree(tmp_path, {})
    assert _layer_violations(_graph(src, mapped)) == []
    assert _typing_violations(src, mapped) == []
    assert _circles(_graph(src, mapped, reach=False)) == []


@pytest.mark.parametrize("hole", sorted(_HOLES))
def test_each_way_of_reaching_the_app_is_found(tmp_path: Path, hole: str) -> None:
    """The three holes of the previous version of this test (``from nirspi_pipe import run``,
    ``nirspi_pipe.run(...)`` after ``import nirspi_pipe``, ``import nirspi_pipe.conf``), a
    renamed import and a TYPE_CHECKING import of the app, each in a runner module."""
    rel, text = _HOLES[hole]
    src, mapped = _facade_tree(tmp_path, {rel: text})
    module = rel.removesuffix(".py").replace("/", ".")
    bad = _layer_violations(_graph(src, mapped)) + _typing_violations(src, mapped)
    assert any(b.startswith(module) for b in bad), (hole, bad)
    if hole == "mapped-conf":
        assert f"{module} -> nirspi_pipe.conf" in bad


def test_an_eager_facade_is_found(tmp_path: Path) -> None:
    """The lazy re-export is what keeps the runner off the app: were the facade to import the
    API at module level, every runner module would reach it through its parent package."""
    eager = _FACADE + "from nirspi_pipe.app.api import run\n"
    src, mapped = _facade_tree(tmp_path, {}, facade=eager)
    bad = _layer_violations(_graph(src, mapped))
    assert "nirspi_pipe.records -> nirspi_pipe -> nirspi_pipe.app.api" in bad
    assert {b.split(" ")[0] for b in bad} == {"nirspi_pipe.pipeline", "nirspi_pipe.records", "nirspi_pipe.stats"}


#: Routes past the previous scan (issue 42: 16 were found from outside), each in a runner module:
#: imports by a string, ``getattr`` on the package, the ``else:`` of ``if TYPE_CHECKING``, code
#: run by ``exec`` from a literal. Each
#: one runs when the module runs, so it must show as a reach (a layer violation), not merely as a
#: name under ``TYPE_CHECKING``. The scan of 8c3f3fd missed each one but the last (it took any
#: ``if TYPE_CHECKING`` inside a function for code that runs; checked when written).
_RUNTIME_HOLES = {
    "import-module": (
        "nirspi_pipe/pipeline.py",
        "import importlib\n\ndef go():\n    importlib.import_module('nirspi_pipe.app.api')\n",
    ),
    "import-module-renamed": ("nirspi_pipe/records.py", "from importlib import import_module as im\n\nim('hydra')\n"),
    "import-module-relative": (
        "nirspi_pipe/pipeline.py",
        "import importlib\n\ndef go():\n    importlib.import_module('.app.api', package='nirspi_pipe')\n",
    ),
    "import-module-concatenated": (
        "nirspi_pipe/pipeline.py",
        "import importlib\n\ndef go():\n    importlib.import_module('nirspi_pipe.' + 'app.api')\n",
    ),
    "import-module-fstring": (
        "nirspi_pipe/pipeline.py",
        "import importlib\n\ndef go(x):\n    importlib.import_module(f'nirspi_pipe.app.{x}')\n",
    ),
    "dunder-import": ("nirspi_pipe/stats.py", "def go():\n    __import__('omegaconf.dictconfig')\n"),
    "dunder-import-fromlist": ("nirspi_pipe/stats.py", "def go():\n    __import__('nirspi_pipe', fromlist=['conf'])\n"),
    "getattr-facade": (
        "nirspi_pipe/pipeline.py",
        "import nirspi_pipe\n\ndef go():\n    getattr(nirspi_pipe, 'run')([])\n",
    ),
    "getattr-import-module": (
        "nirspi_pipe/records.py",
        "import importlib\n\ndef go():\n    getattr(importlib.import_module('nirspi_pipe'), 'run')([])\n",
    ),
    "type-checking-else": (
        "nirspi_pipe/stats.py",
        "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    pass\nelse:\n    from nirspi_pipe.app.api import run\n",
    ),
    "run-module": ("nirspi_pipe/stats.py", "import runpy\n\ndef go():\n    runpy.run_module('nirspi_pipe.app.cli')\n"),
    "resolve-name": (
        "nirspi_pipe/stats.py",
        "from pkgutil import resolve_name\n\ndef go():\n    resolve_name('nirspi_pipe.app.api:run')\n",
    ),
    "exec-literal": ("nirspi_pipe/stats.py", "def go():\n    exec('from nirspi_pipe.app import api')\n"),
    "type-checking-else-in-function": (
        "nirspi_pipe/stats.py",
        "import typing\n\ndef go():\n    if typing.TYPE_CHECKING:\n        pass\n    else:\n        import hydra\n",
    ),
}


@pytest.mark.parametrize("hole", sorted(_RUNTIME_HOLES))
def test_each_route_that_runs_is_a_reach(tmp_path: Path, hole: str) -> None:
    rel, text = _RUNTIME_HOLES[hole]
    src, mapped = _facade_tree(tmp_path, {rel: text})
    module = rel.removesuffix(".py").replace("/", ".")
    bad = _layer_violations(_graph(src, mapped))
    assert any(b.startswith(module + " -> ") for b in bad), (hole, bad)
    assert not any(b.startswith("nirspi_pipe.stats") for b in bad) or module == "nirspi_pipe.stats", bad


@pytest.mark.parametrize(
    "extra",
    [
        "else:\n    from nirspi_pipe.app.api import compose\n",  # after the facade's TYPE_CHECKING block
        "import importlib\nimportlib.import_module('nirspi_pipe.app.api')\n",
        "__import__('nirspi_pipe.app.api')\n",
    ],
)
def test_an_eager_facade_by_any_route_is_found(tmp_path: Path, extra: str) -> None:
    """The facade importing the API at module level by another route: every runner module
    reaches the app through its parent package."""
    head, tail = _FACADE.split("def __getattr__", 1)
    src, mapped = _facade_tree(tmp_path, {}, facade=head + extra + "def __getattr__" + tail)
    assert "nirspi_pipe.records -> nirspi_pipe -> nirspi_pipe.app.api" in _layer_violations(_graph(src, mapped))


def test_what_runs_only_for_a_type_checker_is_no_reach(tmp_path: Path) -> None:
    """The other side: ``if TYPE_CHECKING:`` bodies (at module level or in a function) and the
    ``else:`` of ``if not TYPE_CHECKING:`` are no edge of the reach (the typing rule reports
    them), and an import by a name only known at run time is not guessed."""
    text = (
        "import importlib\nfrom typing import TYPE_CHECKING\n"
        "if not TYPE_CHECKING:\n    import json\nelse:\n    from nirspi_pipe.app.api import run\n"
        "def go(name):\n    if TYPE_CHECKING:\n        import hydra\n    importlib.import_module(name)\n"
    )
    src, mapped = _facade_tree(tmp_path, {"nirspi_pipe/stats.py": text})
    assert not any(b.startswith("nirspi_pipe.stats") for b in _layer_violations(_graph(src, mapped)))
    typing_bad = _typing_violations(src, mapped)
    assert any("imports nirspi_pipe.app.api" in b for b in typing_bad) and any("imports hydra" in b for b in typing_bad)


def test_a_name_the_facade_binds_is_not_lazy(tmp_path: Path) -> None:
    """``from nirspi_pipe import __version__`` (bound at module level) and ``from nirspi_pipe
    import records`` (a submodule) do not run the facade's ``__getattr__``."""
    src, mapped = _facade_tree(tmp_path, {})
    assert "nirspi_pipe.app.api" not in _graph(src, mapped)["nirspi_pipe.stats"]
    assert _graph(src, mapped)["nirspi_pipe.pipeline"] == {"nirspi_pipe", "nirspi_pipe.records"}


def test_plain_config_reads_an_omegaconf_node_as_to_container_does() -> None:
    """The runner's :func:`plain_config` (no OmegaConf import) against OmegaConf's own
    ``to_container(resolve=True)`` on the composed default config and a sweep-like one."""
    from hydra import compose, initialize_config_module
    from omegaconf import OmegaConf

    from nirspi_pipe.app.configs import CONFIG_MODULE, CONFIG_NAME
    from nirspi_pipe.instantiate import plain_config

    with initialize_config_module(CONFIG_MODULE, version_base="1.3"):
        for overrides in ([], ["preset=device", "fog=chamber", "scan=spiral", "itof=cw4", "fusion=itof"]):
            cfg = compose(CONFIG_NAME, overrides=overrides)
            assert plain_config(cfg) == OmegaConf.to_container(cfg, resolve=True)
    node = OmegaConf.create({"a": 1, "b": "${a}", "c": [{"d": "${b}"}, 2.5, None], "e": {"f": "x${a}"}})
    assert plain_config(node) == {"a": 1, "b": 1, "c": [{"d": 1}, 2.5, None], "e": {"f": "x1"}}
    assert type(plain_config(node)["c"]) is list
