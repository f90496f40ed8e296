"""The package's layering: the command line (``segmitsuba/cli/``) uses the library, never the other way round.

Parsed with ``ast``, so imports inside functions and relative imports (``from .cli import ...``,
``from . import cli``) count, and comments or strings that mention ``segmitsuba.cli`` do not."""

from __future__ import annotations

import ast
from collections.abc import Iterator
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parent.parent / "segmitsuba"
#: ``python -m segmitsuba`` runs the command line: the one module outside cli/ that may import it
ENTRY_POINTS = {"segmitsuba/__main__.py"}


def imported_modules(source: str, module: str, is_package: bool = False) -> Iterator[str]:
    """Absolute names of what ``source`` (the code of ``module``) imports: modules, and ``package.name`` for each
    name of a ``from package import name`` (it may be a submodule)."""
    package = module if is_package else module.rpartition(".")[0]
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            yield from (alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                parts = package.split(".")
                base = ".".join(parts[: len(parts) - node.level + 1])
                target = f"{base}.{node.module}" if node.module else base
            else:
                target = node.module or ""
            yield target
            yield from (f"{target}.{alias.name}" for alias in node.names)


def imports_cli(names: Iterator[str]) -> list[str]:
    return [n for n in names if n == "segmitsuba.cli" or n.startswith("segmitsuba.cli.")]


def modules() -> Iterator[tuple[str, Path]]:
    for path in sorted(PACKAGE.rglob("*.py")):
        yield path.relative_to(PACKAGE.parent).as_posix(), path


@pytest.mark.parametrize(
    "source, module, is_package, found",
    [
        ("import segmitsuba.cli", "segmitsuba.x", False, True),
        ("from segmitsuba.cli.common import CliError", "segmitsuba.x", False, True),
        ("from segmitsuba import cli", "segmitsuba.x", False, True),
        ("def f():\n    from .cli import main", "segmitsuba.compare", False, True),
        ("from . import cli", "segmitsuba.compare", False, True),
        ("from .. import cli", "segmitsuba.grid.hashing", False, True),
        ("from ..cli import common", "segmitsuba.grid.hashing", False, True),
        ("from .cli import main", "segmitsuba", True, True),
        ("from . import metrics\nimport segmitsuba.client_tools  # segmitsuba.cli", "segmitsuba.x", False, False),
        ("s = 'from .cli import main'", "segmitsuba.x", False, False),
    ],
)
def test_import_finder(source, module, is_package, found):
    assert bool(imports_cli(imported_modules(source, module, is_package))) == found


def test_library_does_not_import_the_command_line():
    offenders = {}
    for rel, path in modules():
        if rel.startswith("segmitsuba/cli/") or rel in ENTRY_POINTS:
            continue
        module = rel[:-3].replace("/", ".").removesuffix(".__init__")
        names = imports_cli(imported_modules(path.read_text(), module, path.name == "__init__.py"))
        if names:
            offenders[rel] = names
    assert not offenders, f"library modules import segmitsuba.cli: {offenders}"
    # the finder sees the one allowed import, so an empty result above is not a blind spot
    main = PACKAGE / "__main__.py"
    assert imports_cli(imported_modules(main.read_text(), "segmitsuba.__main__"))
