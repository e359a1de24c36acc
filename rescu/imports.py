"""The package's own import graph, read from the source.

The workflow derives each rule's code dependencies from it (a rule reruns when a module
its step imports, at any depth, changes), and ``tests/test_layout.py`` checks with it
that the package has no import cycle. The graph comes from the AST of every module, not
from a running interpreter, so an import inside a function, under ``if TYPE_CHECKING:``
or in a branch that never runs counts as much as one at the top of the file.
"""

from __future__ import annotations

import ast
import functools
from pathlib import Path

PACKAGE_DIR = Path(__file__).resolve().parent
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


def step_dependencies(script: Path, package_dir: Path = PACKAGE_DIR) -> list[Path]:
    """Source files of the package that one workflow script runs, sorted.

    The script's own imports of the package, and for every function of
    ``<package>.pipeline`` it calls (``pipeline.scene(...)`` or ``from rescu.pipeline
    import scene``) the imports inside that function and inside the pipeline functions
    it refers to by name; then everything those import (:func:`import_closure`), plus
    ``pipeline.py`` itself and what it imports at module level. The pipeline imports each
    step's modules inside the step's function, so a step does not depend on the modules
    of the other steps.

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
    pipe_name = f"{pkg}.pipeline"
    pipe_tree = _parsed_module(modules[pipe_name])
    defs = {n.name: n for n in pipe_tree.body
            if isinstance(n, (ast.FunctionDef, ast.ClassDef, ast.AsyncFunctionDef))}
    entries: set[str] = set()
    called: set[str] = set()
    uses_pipeline = False
    for node in ast.walk(ast.parse(Path(script).read_text(), str(script))):
        if isinstance(node, (ast.Import, ast.ImportFrom)):
            for m in _resolve(node, [], modules):
                if m == pipe_name:
                    uses_pipeline = True
                    if isinstance(node, ast.ImportFrom) and node.module == pipe_name:
                        called.update(a.name for a in node.names)
                else:
                    entries.add(m)
        elif (isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name)
              and node.value.id == "pipeline"):
            called.add(node.attr)
    files: set[Path] = set()
    if uses_pipeline:
        files.add(modules[pipe_name])
        package = pipe_name.split(".")[:-1]
        for node in pipe_tree.body:  # what importing the pipeline runs
            if isinstance(node, (ast.Import, ast.ImportFrom)):
                entries.update(m for m in _resolve(node, package, modules) if m != pipe_name)
        todo, seen = [c for c in called if c in defs], set()
        while todo:
            f = todo.pop()
            if f in seen:
                continue
            seen.add(f)
            for node in ast.walk(defs[f]):
                if isinstance(node, (ast.Import, ast.ImportFrom)):
                    entries.update(_resolve(node, package, modules))
                elif isinstance(node, ast.Name) and node.id in defs:
                    todo.append(node.id)
    entries.discard(pipe_name)
    return sorted(files | set(import_closure(sorted(entries), package_dir)))


@functools.lru_cache(maxsize=8)
def _parsed_module(path: Path) -> ast.Module:
    """The AST of one source file, parsed once per process (every rule's stamp asks for
    the pipeline's)."""
    return ast.parse(path.read_text(), str(path))
