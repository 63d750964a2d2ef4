"""The package's layout is its architecture (ARCHITECTURE.md): imports run one way, no cycles, and each
sub-package says what it offers. The import checks read the source (they import none of the checked
modules): every ``import`` statement, at module level or inside a function, and every name a package
``__init__`` exports lazily through ``lazy_exports``."""

from __future__ import annotations

import ast
import importlib
import inspect
import re
from graphlib import CycleError, TopologicalSorter
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = "warp_highlights"

ALLOWED = {
    "model": set(),
    "kernels": {"model"},
    "io": {"model"},
    "quality": {"io", "model"},
    "residual": {"quality", "io", "kernels", "model"},
    "fit": {"residual", "quality", "io", "kernels", "model"},
    "synth": {"io", "kernels", "model"},
    "relight": {"synth", "residual", "quality", "io", "kernels", "model"},
    "view": {"relight", "residual", "quality", "io", "kernels", "model"},
    "web": {"relight", "residual", "quality", "io", "kernels", "model"},
    "collection": {"io", "model"},
    "cli": {"collection", "view", "web", "relight", "fit", "synth", "residual", "quality", "io", "kernels", "model"},
}
"""Which sub-packages each sub-package may import (ARCHITECTURE.md draws the same table)."""

ROOT_MODULES_FOR_ALL = {PACKAGE, f"{PACKAGE}._api"}
"""Every layer may import these: the package root (only for ``__version__``) and the API plumbing."""

FACADE = {PACKAGE, f"{PACKAGE}.__main__"}
"""Above every layer: the package root's lazy API over all sub-packages, and ``python -m``."""

def _module_files() -> dict[str, Path]:
    """Dotted module name -> file, for the package and the kernels (installed as ``warp_highlights.kernels``)."""
    files = {}
    for folder, prefix in ((ROOT / PACKAGE, PACKAGE), (ROOT / "kernels", f"{PACKAGE}.kernels")):
        for path in sorted(folder.rglob("*.py")):
            parts = path.relative_to(folder).with_suffix("").parts
            if parts[-1] == "__init__":
                parts = parts[:-1]
            files[".".join((prefix, *parts))] = path
    return files


MODULES = _module_files()


def _is_package(name: str) -> bool:
    return MODULES[name].name == "__init__.py"


class _Import:
    """One dependency of a module: an import statement, or a name its ``lazy_exports`` table points at."""

    def __init__(self, target: str, line: int, scope: str | None, names: tuple[str, ...], *, lazy: bool = False):
        self.target, self.line, self.scope, self.names, self.lazy = target, line, scope, names, lazy


def _resolve(base: str, level: int, module: str | None) -> str:
    """The absolute name of ``from <level dots><module> import`` written in a module of package ``base``."""
    anchor = base.rsplit(".", level - 1)[0] if level > 1 else base
    return f"{anchor}.{module}" if module else anchor


def _imports(name: str) -> list[_Import]:
    """Every dependency of a module on modules of the package; ``scope`` is the qualified name of the
    function it sits in (``Class.method``), None at module level."""
    tree = ast.parse(MODULES[name].read_text(), filename=str(MODULES[name]))
    base = name if _is_package(name) else name.rpartition(".")[0]
    found = []

    def add_from(source: str, names: tuple[str, ...], line: int, scope, *, lazy=False):
        if source.split(".")[0] != PACKAGE:
            return
        submodules = [f"{source}.{n}" for n in names if f"{source}.{n}" in MODULES]
        for target in submodules or [_known(source)]:
            found.append(_Import(target, line, scope, names, lazy=lazy))

    def visit(node, qualified: str, in_function: bool):
        for child in ast.iter_child_nodes(node):
            scope = qualified if in_function else None
            if isinstance(child, ast.Import):
                for alias in child.names:
                    if alias.name.split(".")[0] == PACKAGE:
                        found.append(_Import(_known(alias.name), child.lineno, scope, ()))
            elif isinstance(child, ast.ImportFrom):
                source = _resolve(base, child.level, child.module) if child.level else (child.module or "")
                add_from(source, tuple(alias.name for alias in child.names), child.lineno, scope)
            elif isinstance(child, ast.Call) and getattr(child.func, "id", None) in ("lazy_exports", "_lazy_exports"):
                for relative, public in _lazy_targets(child):
                    dots = len(relative) - len(relative.lstrip("."))
                    source = _resolve(name, max(dots, 1), relative.lstrip("."))
                    add_from(source.rpartition(".")[0], (source.rpartition(".")[2],), child.lineno, scope, lazy=True)
            if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
                inner = f"{qualified}.{child.name}" if qualified else child.name
                visit(child, inner, in_function or not isinstance(child, ast.ClassDef))
            else:
                visit(child, qualified, in_function)

    visit(tree, "", False)
    return found


def _lazy_targets(call: ast.Call) -> list[tuple[str, str]]:
    """(module written relative to the package, public name) of a ``lazy_exports(__name__, {...},
    modules={...})`` call, evaluated from its source (plain dict literals, ``dict.fromkeys``, and a
    comprehension over a module-level tuple)."""
    tables = [call.args[1]] + [keyword.value for keyword in call.keywords if keyword.arg == "modules"]
    pairs = []
    for table in tables:
        names = {n.id for n in ast.walk(table) if isinstance(n, ast.Name)} - {"dict", "name"}
        assert not names, f"lazy_exports table uses {names}; keep it literal so this test can read it"
        for public, module in eval(compile(ast.Expression(table), "<lazy_exports>", "eval")).items():  # noqa: S307
            pairs.append((module, public))
    return pairs


def _known(name: str) -> str:
    assert name in MODULES, f"import of {name}, which is not a module of the package"
    return name


def _layer(name: str) -> str | None:
    parts = name.split(".")
    return parts[1] if len(parts) > 1 and parts[1] in ALLOWED else None


EDGES = [(name, imp) for name in MODULES for imp in _imports(name) if imp.target != name]


def test_the_walk_sees_lazy_exports_and_imports_inside_functions():
    """Guards the guard: a few edges this file must find, or its other tests would pass vacuously."""
    seen = {(source, imp.target, imp.scope, imp.lazy) for source, imp in EDGES}
    assert (f"{PACKAGE}.model", f"{PACKAGE}.model.field", None, True) in seen
    assert (f"{PACKAGE}.fit", f"{PACKAGE}.kernels.segmentation", None, True) in seen
    assert (f"{PACKAGE}.cli.fit", f"{PACKAGE}.fit.pipeline", "_run_fit", False) in seen
    assert (f"{PACKAGE}.io.fieldfile", PACKAGE, None, False) in seen  # from .. import __version__
    names = {(source, imp.target): imp.names for source, imp in EDGES}
    # the names a from-import takes
    assert "encode_levels" in names[(f"{PACKAGE}.view.animation", f"{PACKAGE}.io.images")]


def test_every_module_is_in_a_layer():
    outside = sorted(n for n in MODULES if _layer(n) is None and n not in FACADE | ROOT_MODULES_FOR_ALL)
    assert not outside, f"modules outside the sub-packages of ARCHITECTURE.md: {outside}"


def test_imports_only_go_down_the_layers():
    wrong = []
    for source, imp in EDGES:
        here, there = _layer(source), _layer(imp.target)
        if source in FACADE:
            continue
        if imp.target in ROOT_MODULES_FOR_ALL:
            if imp.target == PACKAGE and imp.names != ("__version__",):
                wrong.append(f"{source}:{imp.line} imports {imp.names} from the package root (only __version__ may be)")
            continue
        if here is None or there is None:
            wrong.append(f"{source}:{imp.line} imports {imp.target}: one of them is outside the layers")
        elif here != there and there not in ALLOWED[here]:
            wrong.append(f"{source}:{imp.line} ({here}) imports {imp.target} ({there}), which {here} may not")
    assert not wrong, "\n".join(wrong)


def test_the_allowed_imports_form_layers():
    """The table itself has no cycle, so following it can never close one between sub-packages."""
    order = tuple(TopologicalSorter(ALLOWED).static_order())
    assert order[0] == "model" and order[-1] == "cli"


def test_the_model_never_imports_io_and_io_only_the_model():
    for source, imp in EDGES:
        if _layer(source) == "model":
            assert _layer(imp.target) in (None, "model"), (source, imp.line, imp.target)
        if _layer(source) == "io":
            assert _layer(imp.target) in (None, "model", "io"), (source, imp.line, imp.target)


def test_no_import_cycles():
    """Over every module and package ``__init__`` (lazy exports included, and imports inside functions);
    only the facade is left out."""
    graph = {name: set() for name in MODULES if name not in FACADE}
    for source, imp in EDGES:
        if source in FACADE or imp.target in FACADE:
            continue
        graph[source].add(imp.target)
    try:
        tuple(TopologicalSorter(graph).static_order())
    except CycleError as error:
        pytest.fail(f"import cycle: {' -> '.join(error.args[1])}")


def _private(name: str) -> bool:
    """A leading underscore; dunders (``__version__``) are not private."""
    return name.startswith("_") and not (name.startswith("__") and name.endswith("__"))


def private_imports_across_sub_packages(edges) -> list[str]:
    """Each import (statement or lazy export) of a private module or name of one sub-package by another
    (or by the root). Within a sub-package private names are its own business; the root's ``_api``
    belongs to no sub-package (every layer may use its ``lazy_exports``)."""
    wrong = []
    for source, imp in edges:
        there = _layer(imp.target)
        if there is None or _layer(source) == there:
            continue
        private = [part for part in imp.target.split(".")[1:] if _private(part)]
        private += [name for name in imp.names if _private(name) and name not in private]
        if private:
            wrong.append(f"{source}:{imp.line} imports {', '.join(private)} of {imp.target}, private to {there}")
    return wrong


def test_no_private_name_is_imported_from_another_sub_package():
    wrong = private_imports_across_sub_packages(EDGES)
    assert not wrong, "\n".join(wrong)


def test_the_private_check_sees_private_modules_and_names():
    """Guards the guard: made-up imports of a private name, a private module, and a lazy export of one."""
    edges = [
        (f"{PACKAGE}.view.animation", _Import(f"{PACKAGE}.io.images", 1, None, ("_srgb_table",))),
        (f"{PACKAGE}.fit.estimation", _Import(f"{PACKAGE}.kernels._hidden", 2, "f", ("thing",))),
        (f"{PACKAGE}.fit", _Import(f"{PACKAGE}.kernels._hidden", 3, None, ("_hidden",), lazy=True)),
        (f"{PACKAGE}.kernels.raster", _Import(f"{PACKAGE}.kernels._hidden", 4, None, ("_thing",))),  # within kernels
        (f"{PACKAGE}.io.fieldfile", _Import(PACKAGE, 5, None, ("__version__",))),  # a dunder, the root
    ]
    assert [line.split(" ")[0] for line in private_imports_across_sub_packages(edges)] == [
        f"{PACKAGE}.view.animation:1", f"{PACKAGE}.fit.estimation:2", f"{PACKAGE}.fit:3"
    ]


def test_pyproject_lists_every_sub_package():
    text = (ROOT / "pyproject.toml").read_text()
    block = re.search(r"^\[tool\.setuptools\]\s*(?:#[^\n]*\n)?packages = \[(.*?)\]", text, re.S | re.M)
    assert block, "pyproject.toml: [tool.setuptools] packages = [...] not found"
    listed = set(re.findall(r'"([\w.]+)"', block.group(1)))
    assert listed == {name for name in MODULES if _is_package(name)}
    assert re.search(r'^"warp_highlights\.kernels" = "kernels"$', text, re.M)


SUB_PACKAGES = sorted(n for n in MODULES if _is_package(n) and n != PACKAGE)


@pytest.mark.parametrize("name", SUB_PACKAGES)
def test_sub_package_docstring_has_a_line_per_exported_name(name):
    """``__all__`` and the docstring's ``- ``name``: ...`` lines list the same names."""
    package = importlib.import_module(name)
    documented = re.findall(r"^- ``(\w+)``:", inspect.getdoc(package) or "", re.M)
    assert len(documented) == len(set(documented)), f"{name}: a name has two lines"
    assert sorted(documented) == sorted(package.__all__)


@pytest.mark.parametrize("name", [PACKAGE, *SUB_PACKAGES])
def test_exported_names_resolve_within_the_layer(name):
    """Each name in ``__all__`` resolves, to something defined in the package's layer or one it may import."""
    package = importlib.import_module(name)
    assert len(set(package.__all__)) == len(package.__all__)
    for public in package.__all__:
        value = getattr(package, public)
        defined_in = value.__name__ if inspect.ismodule(value) else getattr(value, "__module__", None)
        if name != PACKAGE and defined_in and defined_in.startswith(PACKAGE):
            here, there = _layer(name), _layer(defined_in)
            assert there == here or there in ALLOWED[here], f"{name}.{public} comes from {defined_in}"


def test_exported_functions_are_not_shadowed_by_modules():
    """With every module imported, a package's exported name is still the object, not a same-named module."""
    for name in MODULES:
        if not name.endswith("__main__"):  # importing __main__ would run the command line
            importlib.import_module(name)
    for name in [PACKAGE, *SUB_PACKAGES]:
        package = importlib.import_module(name)
        for public in package.__all__:
            value = getattr(package, public)
            shadowed = inspect.ismodule(value) and hasattr(value, public)
            assert not shadowed, f"{name}.{public} is the module {value.__name__}, not the {public} it defines"
