"""The project's imports as its source writes them, read with `ast` (nothing is imported): for
the tests that hold the layers (tests/test_layers.py) and each role's packages
(tests/packaging/test_imports.py)."""

import ast
from collections.abc import Iterator
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[2]


def source_files(package: str) -> Iterator[Path]:
    """The package's Python files, migrations left out."""
    for path in sorted((REPO_ROOT / package).rglob("*.py")):
        if "migrations" not in path.parts:
            yield path


def imports(path: Path) -> Iterator[tuple[str, bool, int]]:
    """(imported module, imported inside a function, line) for each import of the file."""
    tree = ast.parse(path.read_text(), filename=str(path))
    local_lines = {
        node.lineno
        for function in ast.walk(tree)
        if isinstance(function, ast.FunctionDef | ast.AsyncFunctionDef)
        for node in ast.walk(function)
        if isinstance(node, ast.Import | ast.ImportFrom)
    }
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                yield alias.name, node.lineno in local_lines, node.lineno
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            for alias in node.names:
                # `from sharing import services` imports the module sharing.services.
                yield f"{node.module}.{alias.name}", node.lineno in local_lines, node.lineno
