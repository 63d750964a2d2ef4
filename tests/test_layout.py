"""The package's layout is its architecture (ARCHITECTURE.md): imports run one way, no cycles, and each
sub-package says what it offers. Static checks over the source (no imports of the checked modules,
except where a test says so)."""

from __future__ import annotations

import ast
import importlib
import inspect
from graphlib import CycleError, TopologicalSorter
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = "warp_highlights"

ALLOWED = {
    "model": set(),
    "kernels": {"model"},
    "io": {"model"},
    "fit": {"io", "kernels", "model"},
    "synth": {"io", "kernels", "model"},
    "relight": {"synth", "io", "kernels", "model"},
    "view": {"relight", "io", "kernels", "model"},
    "cli": {"view", "relight", "fit", "synth", "io", "kernels", "model"},
}
"""Which sub-packages each sub-package may import (ARCHITECTURE.md draws the same table)."""
LAYERS = set(ALLOWED)

ROOT_MODULES_FOR_ALL = {f"{PACKAGE}", f"{PACKAGE}._api"}
"""Every layer may import these: the package root (only for ``__version__``) and the API plumbing."""

DEPRECATED_FORWARDS = {
    (f"{PACKAGE}.model.field", f"{PACKAGE}.io.fieldfile"): {"save", "load", "size_report"},
    (f"{PACKAGE}.model.field", f"{PACKAGE}.relight.relighter"): {"relight"},
    (f"{PACKAGE}.model.lights", f"{PACKAGE}.io.lightfile"): {"read_lp", "write_lp"},
}
"""The only upward imports: inside the deprecated methods that forward to where things moved (removed
in 0.3). Each must sit in one of the named methods, and each method must warn."""


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
    def __init__(self, target: str, line: int, function: str | None, names: tuple[str, ...]):
        self.target, self.line, self.function, self.names = target, line, function, names


def _imports(name: str) -> list[_Import]:
    """Every import in a module (module level and inside functions), resolved to modules of the package."""
    tree = ast.parse(MODULES[name].read_text(), filename=str(MODULES[name]))
    base = name if _is_package(name) else name.rpartition(".")[0]
    found = []

    def visit(node, function):
        for child in ast.iter_child_nodes(node):
            inner = child.name if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef)) else function
            if isinstance(child, ast.Import):
                for alias in child.names:
                    if alias.name.split(".")[0] == PACKAGE:
                        found.append(_Import(_known(alias.name), child.lineno, function, ()))
            elif isinstance(child, ast.ImportFrom):
                if child.level:
                    anchor = base.rsplit(".", child.level - 1)[0] if child.level > 1 else base
                    source = f"{anchor}.{child.module}" if child.module else anchor
                else:
                    source = child.module or ""
                if source.split(".")[0] != PACKAGE:
                    continue
                names = tuple(alias.name for alias in child.names)
                submodules = [f"{source}.{n}" for n in names if f"{source}.{n}" in MODULES]
                for target in submodules or [_known(source)]:
                    found.append(_Import(target, child.lineno, function, names))
            visit(child, inner)

    visit(tree, None)
    return found


def _known(name: str) -> str:
    assert name in MODULES, f"import of {name}, which is not a module of the package"
    return name


def _layer(name: str) -> str | None:
    parts = name.split(".")
    return parts[1] if len(parts) > 1 and parts[1] in LAYERS else None


def _edges() -> list[tuple[str, _Import]]:
    return [(name, imp) for name in MODULES for imp in _imports(name) if imp.target != name]


def test_every_module_is_in_a_layer():
    outside = sorted(n for n in MODULES if _layer(n) is None and n not in {PACKAGE, f"{PACKAGE}._api", f"{PACKAGE}.__main__"})
    assert not outside, f"modules outside the sub-packages of ARCHITECTURE.md: {outside}"


def test_imports_only_go_down_the_layers():
    wrong = []
    for source, imp in _edges():
        here, there = _layer(source), _layer(imp.target)
        if imp.target in ROOT_MODULES_FOR_ALL:
            if imp.target == PACKAGE and imp.names != ("__version__",):
                wrong.append(f"{source}:{imp.line} imports {imp.names} from the package root (only __version__ may be)")
            continue
        if source == f"{PACKAGE}.__main__" and there == "cli":
            continue
        if here is None:
            wrong.append(f"{source}:{imp.line} (outside the layers) imports {imp.target}")
        elif there is None:
            wrong.append(f"{source}:{imp.line} imports {imp.target}, which is outside the layers")
        elif here != there and there not in ALLOWED[here]:
            methods = DEPRECATED_FORWARDS.get((source, imp.target), set())
            if imp.function not in methods:
                wrong.append(f"{source}:{imp.line} ({here}) imports {imp.target} ({there}), which {here} may not")
    assert not wrong, "\n".join(wrong)


def test_the_allowed_imports_form_layers():
    """The table itself has no cycle, so following it can never close one between sub-packages."""
    order = tuple(TopologicalSorter(ALLOWED).static_order())
    assert order[0] == "model" and order[-1] == "cli"


def test_the_model_never_imports_io_and_io_only_the_model():
    for source, imp in _edges():
        if _layer(source) == "model" and _layer(imp.target) not in (None, "model"):
            assert (source, imp.target) in DEPRECATED_FORWARDS and imp.function is not None, (source, imp.target)
        if _layer(source) == "io":
            assert _layer(imp.target) in (None, "model", "io"), (source, imp.line, imp.target)


def test_no_import_cycles():
    graph = {name: set() for name in MODULES}
    for source, imp in _edges():
        if (source, imp.target) not in DEPRECATED_FORWARDS:
            graph[source].add(imp.target)
    # a package's __init__ may re-export its modules; a module importing its own package's __init__
    # for a name is what would close a cycle, and that shows up here too
    try:
        tuple(TopologicalSorter(graph).static_order())
    except CycleError as error:
        pytest.fail(f"import cycle: {' -> '.join(error.args[1])}")


def test_deprecated_forwards_warn():
    """Each allowed upward import sits in a method that calls ``warn_moved`` before anything else."""
    for (source, target), methods in DEPRECATED_FORWARDS.items():
        tree = ast.parse(MODULES[source].read_text())
        defined = {
            node.name: node for node in ast.walk(tree) if isinstance(node, ast.FunctionDef) and node.name in methods
        }
        assert set(defined) == methods, (source, methods - set(defined))
        for method, node in defined.items():
            body = node.body[1:] if isinstance(node.body[0].value if isinstance(node.body[0], ast.Expr) else None, ast.Constant) else node.body
            first = body[0]
            assert (
                isinstance(first, ast.Expr)
                and isinstance(first.value, ast.Call)
                and getattr(first.value.func, "id", None) == "warn_moved"
            ), f"{source}.{method} must call warn_moved first"


def test_pyproject_lists_every_sub_package():
    tomllib = pytest.importorskip("tomllib", reason="tomllib is in the standard library from Python 3.11")
    config = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
    on_disk = {name for name in MODULES if _is_package(name)}
    assert set(config["packages"]) == on_disk
    assert config["package-dir"][f"{PACKAGE}.kernels"] == "kernels"


SUB_PACKAGES = sorted(n for n in MODULES if _is_package(n) and n != PACKAGE)


@pytest.mark.parametrize("name", [PACKAGE, *SUB_PACKAGES])
def test_sub_package_offers_what_it_names(name):
    """``__all__`` resolves name by name, to a definition in the package's layer or below, and every
    sub-package's docstring has a line per name."""
    package = importlib.import_module(name)
    doc = inspect.getdoc(package) or ""
    for public in package.__all__:
        value = getattr(package, public)
        assert value is not None, public
        if name != PACKAGE:
            assert f"``{public}``" in doc, f"{name}: __all__ names {public} but the docstring has no line for it"
        defined_in = value.__name__ if inspect.ismodule(value) else getattr(value, "__module__", None)
        if defined_in and defined_in.startswith(PACKAGE) and name != PACKAGE:
            here, there = _layer(name), _layer(defined_in)
            assert there == here or there in ALLOWED[here], f"{name}.{public} comes from {defined_in}"
    assert len(set(package.__all__)) == len(package.__all__)


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
