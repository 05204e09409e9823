"""The package rules of docs/architecture.md that a linter does not check.

import-linter (``make lint``) forbids ``radiokit`` importing ``sim`` or ``acquisition``; this test
forbids any of the three packages importing a private name (a module or attribute whose name starts
with ``_``) of another: a private name may change without notice, so crossing a package boundary
through one is a contract nobody wrote down.
"""
import ast
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PACKAGES = ("radiokit", "sim", "acquisition")


def _private(name: str) -> bool:
    return name.startswith("_") and not name.startswith("__")


def _cross_package_private_imports(path: Path, package: str) -> list[str]:
    found = []
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), filename=str(path))):
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            parts = node.module.split(".")
            if parts[0] in PACKAGES and parts[0] != package:
                names = [a.name for a in node.names]
                if any(map(_private, parts[1:])) or any(map(_private, names)):
                    found.append(f"{path.relative_to(REPO)}:{node.lineno}: from {node.module} import {', '.join(names)}")
        elif isinstance(node, ast.Import):
            for alias in node.names:
                parts = alias.name.split(".")
                if parts[0] in PACKAGES and parts[0] != package and any(map(_private, parts[1:])):
                    found.append(f"{path.relative_to(REPO)}:{node.lineno}: import {alias.name}")
    return found


@pytest.mark.parametrize("package", PACKAGES)
def test_no_private_name_is_imported_across_packages(package):
    found = [hit for path in sorted((REPO / package).rglob("*.py"))
             for hit in _cross_package_private_imports(path, package)]
    assert not found, "private names imported across packages:\n" + "\n".join(found)


def test_the_check_can_fail(tmp_path):
    (tmp_path / "m.py").write_text("from radiokit.io._itex import parse_comment\nimport radiokit._version\n")
    global REPO
    saved, REPO = REPO, tmp_path
    try:
        assert len(_cross_package_private_imports(tmp_path / "m.py", "sim")) == 2
        assert _cross_package_private_imports(tmp_path / "m.py", "radiokit") == []
    finally:
        REPO = saved
