"""The ``rescu`` package's own import graph, read from the source.

The workflow derives each rule's code dependencies from it (a rule reruns when a module
its step imports, at any depth, changes), and ``tests/test_layout.py`` checks with it
that the package has no import cycle. The graph comes from the AST of every module, not
from a running interpreter, so an import inside a function, under ``if TYPE_CHECKING:``
or in a branch that never runs counts as much as one at the top of the file.
"""

from __future__ import annotations

import ast
import functools
import importlib.util
from pathlib import Path


def _package_dir(name: str = "rescu") -> Path:
    """The folder of an installed package, found without importing it."""
    spec = importlib.util.find_spec(name)
    if spec is None or not spec.submodule_search_locations:
        raise ImportError(f"package {name!r} not found")
    return Path(list(spec.submodule_search_locations)[0]).resolve()


PACKAGE_DIR = _package_dir()
"""The folder of the ``rescu`` package."""


def package_modules(package_dir: Path = PACKAGE_DIR) -> dict[str, Path]:
    """Dotted module name -> source file, for every ``.py`` under ``package_dir``.

    A package is its ``__init__.py`` (``rescu.scene.vp`` -> ``rescu/scene/vp/__init__.py``);
    names start with the package folder's name.
    """
    out = {}
    for p in sorted(package_dir.rglob("*.py")):
        parts = list(p.relative_to(package_dir.parent).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out[".".join(parts)] = p
    return out


def module_imports(name: str, path: Path, modules: dict[str, Path]) -> list[tuple[str, int]]:
    """(imported module of ``modules``, line) of every import statement in one module.

    Imports at any depth count. ``from package import name`` is an import of the
    submodule ``package.name`` when there is one, else of the package; relative imports
    are resolved against the module's package. Self-imports and modules outside
    ``modules`` are left out.
    """
    is_pkg = path.name == "__init__.py"
    package = name.split(".") if is_pkg else name.split(".")[:-1]
    out = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            out += [(a.name, node.lineno) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package[:len(package) - (node.level - 1)]
                mod = ".".join(base + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
            for a in node.names:
                sub = f"{mod}.{a.name}"
                out.append((sub if sub in modules else mod, node.lineno))
    return [(m, line) for m, line in out if m in modules and m != name]


def import_graph(package_dir: Path = PACKAGE_DIR) -> dict[str, dict[str, int]]:
    """{module: {imported module of the package: first line}} over the whole package.

    Parsed afresh on every call (see :func:`import_closure` for the cached use).
    """
    modules = package_modules(package_dir)
    graph: dict[str, dict[str, int]] = {}
    for name, path in modules.items():
        edges: dict[str, int] = {}
        for m, line in module_imports(name, path, modules):
            edges.setdefault(m, line)
        graph[name] = edges
    return graph


def import_closure(names: list[str] | tuple[str, ...],
                   package_dir: Path = PACKAGE_DIR) -> list[Path]:
    """Source files of the modules ``names`` and of every package module they import,
    directly or not, sorted.

    Parameters
    ----------
    names : sequence of str
        Dotted module names (``"rescu.scene.analyse"``); a package name stands for its
        ``__init__.py``.

    Returns
    -------
    list of Path, one per module reached (each file once).

    Raises
    ------
    KeyError naming a module that is not in the package.

    Examples
    --------
    >>> files = import_closure(["rescu.params"])
    >>> [f.name for f in files]
    ['params.py']
    """
    modules, graph = _parsed(package_dir)
    missing = [n for n in names if n not in modules]
    if missing:
        raise KeyError(f"not a module of {package_dir.name}: {missing}")
    seen: set[str] = set()
    todo = list(names)
    while todo:
        m = todo.pop()
        if m not in seen:
            seen.add(m)
            todo += graph[m]
    return sorted(modules[m] for m in seen)


@functools.lru_cache(maxsize=4)
def _parsed(package_dir: Path) -> tuple[dict[str, Path], dict[str, dict[str, int]]]:
    """(modules, graph) of one package folder, parsed once per process (the workflow
    asks for a closure per rule while it loads)."""
    return package_modules(package_dir), import_graph(package_dir)


def _resolve(node: ast.ImportFrom | ast.Import, package: list[str],
             modules: dict[str, Path]) -> list[str]:
    """The package modules one import statement names (relative ones resolved against
    ``package``, the importing module's package as a list of name parts)."""
    if isinstance(node, ast.Import):
        return [a.name for a in node.names if a.name in modules]
    if node.level:
        base = package[:len(package) - (node.level - 1)]
        mod = ".".join(base + ([node.module] if node.module else []))
    else:
        mod = node.module or ""
    out = []
    for a in node.names:
        sub = f"{mod}.{a.name}"
        out.append(sub if sub in modules else mod)
    return [m for m in out if m in modules]


#: modules whose functions are the steps: a step depends on the functions it calls in
#: them, not on everything they import (``rescu.pipeline`` reads and writes one step's
#: files, ``rescu.core`` computes it)
STEP_MODULES = ("pipeline", "core")


def step_dependencies(script: Path, package_dir: Path = PACKAGE_DIR) -> list[Path]:
    """Source files of the package that one workflow script runs, sorted.

    The script's own imports of the package, and for every function of a step module
    (:data:`STEP_MODULES`: ``pipeline``, ``core``) it calls (``pipeline.scene(...)``,
    ``from rescu.pipeline import scene``) the imports inside that function and the
    functions of the step modules it refers to (by name, ``core.analyse_scene``, or a
    name imported from another step module), followed in turn; then everything those
    import (:func:`import_closure`), plus each step module used and what it imports at
    module level (other than step modules). The step modules import each step's
    modules inside the step's function, so a step does not depend on the modules of the
    other steps.

    Parameters
    ----------
    script : Path
        A Python file (a Snakemake ``script:`` adapter).

    Returns
    -------
    list of Path (each file once).
    """
    modules, _ = _parsed(package_dir)
    pkg = package_dir.name
    steps = [f"{pkg}.{m}" for m in STEP_MODULES if f"{pkg}.{m}" in modules]
    trees = {m: _parsed_module(modules[m]) for m in steps}
    defs = {(m, n.name): n for m in steps for n in trees[m].body
            if isinstance(n, (ast.FunctionDef, ast.ClassDef, ast.AsyncFunctionDef))}

    def bindings(body: list[ast.stmt] | ast.AST, package: list[str]) -> tuple[
            dict[str, str], dict[str, tuple[str, str]], set[str]]:
        """Module aliases, aliases of step functions, other package modules imported."""
        mods, funcs, other = {}, {}, set()
        nodes = body if isinstance(body, list) else list(ast.walk(body))
        for node in nodes:
            if not isinstance(node, (ast.Import, ast.ImportFrom)):
                continue
            for m in _resolve(node, package, modules):
                if m not in steps:
                    other.add(m)
            if isinstance(node, ast.Import):
                continue
            base = ".".join(package[:len(package) - (node.level - 1)]
                            + ([node.module] if node.module else [])) if node.level \
                else (node.module or "")
            for a in node.names:
                sub = f"{base}.{a.name}"
                if sub in steps:
                    mods[a.asname or a.name] = sub
                elif base in steps:
                    funcs[a.asname or a.name] = (base, a.name)
        return mods, funcs, other

    package = [pkg]
    script_tree = ast.parse(Path(script).read_text(), str(script))
    mods, funcs, entries = bindings(script_tree, [])
    env = {m: bindings(trees[m].body, package)[:2] for m in steps}
    todo: list[tuple[str, str]] = list(funcs.values())
    todo += [(mods[n.value.id], n.attr) for n in ast.walk(script_tree)
             if isinstance(n, ast.Attribute) and isinstance(n.value, ast.Name)
             and n.value.id in mods]
    used = {m for m in steps if m in mods.values() or any(m == f[0] for f in funcs.values())}
    seen: set[tuple[str, str]] = set()
    while todo:
        key = todo.pop()
        if key in seen or key not in defs:
            continue
        seen.add(key)
        m = key[0]
        used.add(m)
        m_mods, m_funcs = env[m]
        f_mods, f_funcs, f_other = bindings(defs[key], package)
        entries |= f_other
        for node in ast.walk(defs[key]):
            if isinstance(node, ast.Name):
                if (m, node.id) in defs:
                    todo.append((m, node.id))
                elif node.id in m_funcs or node.id in f_funcs:
                    todo.append({**m_funcs, **f_funcs}[node.id])
            elif isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name):
                target = {**m_mods, **f_mods}.get(node.value.id)
                if target is not None:
                    todo.append((target, node.attr))
    files = {modules[m] for m in used}
    for m in used:  # what importing the step module runs
        entries |= bindings(trees[m].body, package)[2]
    return sorted(files | set(import_closure(sorted(entries), package_dir)))


@functools.lru_cache(maxsize=8)
def _parsed_module(path: Path) -> ast.Module:
    """The AST of one source file, parsed once per process (every rule's stamp asks for
    the pipeline's)."""
    return ast.parse(path.read_text(), str(path))
