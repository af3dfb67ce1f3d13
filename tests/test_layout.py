"""The library's layout stays walkable (README "Layout"): every file one concept of at most
500 lines, imports that only run down the floors, no circle, and the paper's machinery
above the library."""

import ast
from pathlib import Path

import pytest
from conftest import REPO_ROOT

MAX_LINES = 500
PACKAGES = ("gld", "data")
LIBRARY = sorted(path for package in PACKAGES for path in (REPO_ROOT / package).rglob("*.py"))


def _module(path: Path) -> str:
    parts = path.relative_to(REPO_ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _imports(path: Path) -> tuple[set[str], list[str]]:
    """(the project modules `path` imports at its top level, those it imports inside a
    function)."""
    tree = ast.parse(path.read_text())
    top, local = set(), []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names = [node.module] + [f"{node.module}.{alias.name}" for alias in node.names]
        else:
            continue
        own = [name for name in names if name.split(".")[0] in PACKAGES]
        if node in tree.body or _in_module_body(tree, node):
            top.update(own)
        else:
            local.extend(own)
    return top, local


def _in_module_body(tree: ast.Module, node: ast.AST) -> bool:
    """Whether `node` runs when the module is imported (not inside a function)."""
    stack = list(tree.body)
    while stack:
        item = stack.pop()
        if item is node:
            return True
        if isinstance(item, ast.FunctionDef | ast.AsyncFunctionDef | ast.Lambda):
            continue
        stack.extend(ast.iter_child_nodes(item))
    return False


MODULES = {_module(path): path for path in LIBRARY}


def _graph() -> dict[str, set[str]]:
    graph = {}
    for name, path in MODULES.items():
        top, _ = _imports(path)
        graph[name] = {target for target in top if target in MODULES and target != name}
    return graph


def test_the_layout_sees_the_library():
    assert {"gld.models.global_local", "gld.runs.config", "gld.paper.suite"} <= set(MODULES)
    assert len(MODULES) > 80


@pytest.mark.parametrize("path", LIBRARY, ids=lambda path: str(path.relative_to(REPO_ROOT)))
def test_every_library_file_is_at_most_500_lines(path: Path):
    lines = len(path.read_text().splitlines())
    assert lines <= MAX_LINES, (
        f"{path.relative_to(REPO_ROOT)} has {lines} lines: split it by concept (README, Layout)"
    )


def _circles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The import circles of `graph` found by a depth-first walk, each as the modules
    along it (first = last)."""
    circles, done, on_path = [], set(), []

    def visit(name: str) -> None:
        if name in on_path:
            circles.append(on_path[on_path.index(name) :] + [name])
            return
        if name in done:
            return
        on_path.append(name)
        for target in sorted(graph[name]):
            # A package's __init__ importing its own modules is how a package is made.
            if not target.startswith(name + "."):
                visit(target)
        on_path.pop()
        done.add(name)

    for name in sorted(graph):
        visit(name)
    return circles


def test_no_import_circle():
    circles = _circles(_graph())
    assert not circles, "import circle(s): " + "; ".join(" -> ".join(c) for c in circles)


def test_the_paper_machinery_depends_on_the_library_never_the_reverse():
    for name, targets in _graph().items():
        if not name.startswith("gld.paper"):
            assert not [t for t in targets if t.startswith("gld.paper")], name


def test_the_library_imports_its_own_modules_at_the_top():
    """A function-local import of a project module hides an arrow of the graph; none is
    left in gld/ (data/'s builders import gld's pieces lazily, for TFDS's discovery)."""
    hidden = {
        name: local
        for name, path in MODULES.items()
        if name.startswith("gld") and (local := _imports(path)[1])
    }
    assert not hidden


def test_the_checks_would_see_a_circle_and_a_hidden_import(tmp_path):
    """The checks above read real imports: a planted circle and a function-local import
    are found."""
    first, second = tmp_path / "gld" / "first.py", tmp_path / "gld" / "second.py"
    first.parent.mkdir()
    first.write_text("from gld import second\n")
    second.write_text("import gld.first\n\ndef f():\n    from gld import flow\n")
    assert _imports(first)[0] >= {"gld", "gld.second"}
    assert _imports(second) == ({"gld.first"}, ["gld", "gld.flow"])
    graph = {"gld.first": {"gld.second"}, "gld.second": {"gld.first"}, "gld.third": set()}
    assert _circles(graph) == [["gld.first", "gld.second", "gld.first"]]
