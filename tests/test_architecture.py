"""The package rules of docs/architecture.md that a linter does not check.

import-linter (``make lint``) forbids ``radiokit`` importing ``sim`` or ``acquisition``; this test
forbids any of the three packages importing a private name (a module or attribute whose name starts
with ``_``) of another: a private name may change without notice, so crossing a package boundary
through one is a contract nobody wrote down. It also keeps functions short (or explained) and
named int constants enums.
"""

import ast
import contextlib
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
                    found.append(
                        f"{path.relative_to(REPO)}:{node.lineno}: from {node.module} import {', '.join(names)}"
                    )
        elif isinstance(node, ast.Import):
            for alias in node.names:
                parts = alias.name.split(".")
                if parts[0] in PACKAGES and parts[0] != package and any(map(_private, parts[1:])):
                    found.append(f"{path.relative_to(REPO)}:{node.lineno}: import {alias.name}")
    return found


@pytest.mark.parametrize("package", PACKAGES)
def test_no_private_name_is_imported_across_packages(package):
    found = [
        hit for path in sorted((REPO / package).rglob("*.py")) for hit in _cross_package_private_imports(path, package)
    ]
    assert not found, "private names imported across packages:\n" + "\n".join(found)


@contextlib.contextmanager
def _repo_at(folder: Path):
    """The checks' paths taken relative to ``folder`` while the block runs."""
    global REPO
    saved, REPO = REPO, folder
    try:
        yield
    finally:
        REPO = saved


def test_the_check_can_fail(tmp_path):
    (tmp_path / "m.py").write_text("from radiokit.io._itex import parse_comment\nimport radiokit._version\n")
    with _repo_at(tmp_path):
        assert len(_cross_package_private_imports(tmp_path / "m.py", "sim")) == 2
        assert _cross_package_private_imports(tmp_path / "m.py", "radiokit") == []


def _names_imported_from(module: str, root: Path, package: str = "radiokit") -> list[str]:
    """``path:line: name`` for every name that ``package``'s modules, other than ``module`` itself,
    import from ``module`` (absolute imports: the package uses no relative ones)."""
    found = []
    for path in sorted((root / package).rglob("*.py")):
        if ".".join(path.relative_to(root).with_suffix("").parts) == module:
            continue
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), filename=str(path))):
            if isinstance(node, ast.ImportFrom) and node.module == module:
                found += [f"{path.relative_to(root).as_posix()}:{node.lineno}: {a.name}" for a in node.names]
    return found


def test_the_report_is_used_through_its_public_interface():
    """The pipeline draws the report's figures and writes its page in two steps (its total is taken
    between them): through names in ``radiokit.report.__all__``, never its private helpers. Other
    modules of radiokit still import private names of measure, register, io and pipeline (review s44)."""
    import radiokit.report

    public = set(radiokit.report.__all__)
    found = [hit for hit in _names_imported_from("radiokit.report", REPO) if hit.rsplit(" ", 1)[1] not in public]
    assert not found, "names imported from radiokit.report outside its __all__:\n" + "\n".join(found)


def test_the_report_check_can_fail(tmp_path):
    (tmp_path / "radiokit").mkdir()
    (tmp_path / "radiokit" / "m.py").write_text("from radiokit.report import _draw, write_report\n")
    assert [h.rsplit(" ", 1)[1] for h in _names_imported_from("radiokit.report", tmp_path)] == ["_draw", "write_report"]


# -- no private name crosses a module ----------------------------------------------------------------
# A module of a package (radiokit.pipeline, radiokit.io with all its files, sim.mesh) uses another's
# names through its public interface: a leading "_" says the name may change with its module alone.
# What is found is ``"importer.py: owner.name"``, once per file (lines move). Private modules of a
# package itself (radiokit._json, radiokit._threads) are the whole package's; a private submodule
# reached for a public name (``from radiokit.io._budget import BUDGET_ENV``) is not looked at here.
# Private names still used across modules; the list may only shrink: an entry fails once it is gone.
ALLOWED_PRIVATE = {
    # acquisition drives the X-ray source: its interfaces change under its own review. Both are
    # candidates for a public name there: the resume reader its command asks before starting, and
    # the write of the guardian's READY line that survives a reader gone (review s44priv)
    "acquisition/cli.py: acquisition.protocols.compression_series._existing",
    "acquisition/guardian.py: acquisition.transport._write_no_sigpipe",
    # the rasteriser behind sim.xray.render, which sim.truth drives with power=2 and (K, m) weights
    # to integrate fields along the rays: raw vertices, faces and the geometry's private grid are
    # no interface for a user, and both modules are the one projection's physics
    "sim/truth.py: sim.xray._render",
}


def _unit(module: str) -> str:
    """The module a name belongs to: ``radiokit.io._budget`` -> ``radiokit.io``, ``sim.mesh`` -> itself."""
    return ".".join(module.split(".")[:2])


def _private_uses(path: Path, root: Path) -> set[str]:
    """``"path: owner.name"`` for each private name of another module of ``path``'s package that
    ``path`` imports (``from radiokit.measure import _x``, ``from radiokit.io import _budget``,
    ``import radiokit.io._budget``) or reaches as an attribute of a name it imported
    (``_budget._share``, ``measure._x``, ``y._z`` after ``import radiokit.io._x as y``). Relative
    imports are not used in these packages. Not seen: a name reached through ``importlib`` or
    ``getattr`` with a string, and an instance's attribute (``src._h5`` of a FrameSource passed
    in): the check reads names, not types; review finds those."""
    rel = path.relative_to(root).with_suffix("")
    package = rel.parts[0]
    here = _unit(".".join(rel.parts[:-1] if rel.name == "__init__" else rel.parts))
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    bound, found = {}, set()

    def check(owner: str, name: str):
        if _private(name) and owner != package and _unit(owner) != here:
            found.add(f"{rel.as_posix()}.py: {owner}.{name}")

    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.level == 0 and (node.module or "").split(".")[0] == package:
            for a in node.names:
                check(node.module, a.name)
                bound[a.asname or a.name] = f"{node.module}.{a.name}"
        elif isinstance(node, ast.Import):
            for a in (a for a in node.names if a.name.split(".")[0] == package):
                owner, _, name = a.name.rpartition(".")
                if owner:
                    check(owner, name)
                bound[a.asname or package] = a.name if a.asname else package
    for node in ast.walk(tree):
        if isinstance(node, ast.Attribute):
            chain, value = [node.attr], node.value
            while isinstance(value, ast.Attribute):
                chain, value = [value.attr, *chain], value.value
            if isinstance(value, ast.Name) and value.id in bound:
                check(".".join([bound[value.id], *chain[:-1]]), chain[-1])
    return found


def test_no_private_name_crosses_a_module():
    found = {
        hit
        for package in PACKAGES
        for path in sorted((REPO / package).rglob("*.py"))
        for hit in _private_uses(path, REPO)
    }
    new, gone = sorted(found - ALLOWED_PRIVATE), sorted(ALLOWED_PRIVATE - found)
    assert not new, "private names used across modules (give them a public name):\n" + "\n".join(new)
    assert not gone, "no longer used: remove from ALLOWED_PRIVATE:\n" + "\n".join(gone)


def test_the_private_name_check_can_fail(tmp_path):
    (tmp_path / "radiokit" / "io").mkdir(parents=True)
    (tmp_path / "radiokit" / "io" / "_a.py").write_text("from radiokit.io._b import _inside\n")
    (tmp_path / "radiokit" / "m.py").write_text(
        "from radiokit import _json\nfrom radiokit._threads import cores\nfrom radiokit.io._b import PUBLIC\n"
        "from radiokit.measure import _x, ROI\nfrom radiokit.io import _budget\nimport radiokit.register._auto\n"
        "import radiokit.pipeline as p\nimport radiokit\nimport radiokit.io._atomic as y\ny._remove\n"
        "_budget._share, ROI._pair, p._run(), radiokit.report._draw, radiokit.report.write, _json._strict\n"
    )
    assert _private_uses(tmp_path / "radiokit" / "io" / "_a.py", tmp_path) == set()
    assert sorted(_private_uses(tmp_path / "radiokit" / "m.py", tmp_path)) == [
        f"radiokit/m.py: {name}"
        for name in (
            "radiokit._json._strict",
            "radiokit.io._atomic",
            "radiokit.io._atomic._remove",
            "radiokit.io._budget",
            "radiokit.io._budget._share",
            "radiokit.measure.ROI._pair",
            "radiokit.measure._x",
            "radiokit.pipeline._run",
            "radiokit.register._auto",
            "radiokit.report._draw",
        )
    ]


# -- functions stay short ------------------------------------------------------------------------
MAX_CODE_LINES = 60
LONG_REASON = "Long because"
CHECKED = ("radiokit", "acquisition")
# Functions allowed to stay long without a "Long because" line (none today); an entry fails once
# it is no longer long, so the list cannot go stale.
ALLOWED_LONG: set[str] = set()


def _code_lines(node: ast.FunctionDef | ast.AsyncFunctionDef, lines: list[str]) -> int:
    """Lines of the function's body that hold code: not blank, not only a comment, not the
    docstring (the signature and decorators do not count; nested functions do)."""
    body = node.body
    start = body[0].lineno
    if ast.get_docstring(node, clean=False) is not None:
        start = body[0].end_lineno + 1
    return sum(1 for text in lines[start - 1 : node.end_lineno] if text.strip() and not text.strip().startswith("#"))


def _long_functions(root: Path, packages=CHECKED) -> dict[str, tuple[int, bool]]:
    """``{"pkg/module.py:name": (code lines, has a "Long because" line in its docstring)}`` for
    every function over :data:`MAX_CODE_LINES`."""
    found = {}
    for package in packages:
        for path in sorted((root / package).rglob("*.py")):
            text = path.read_text(encoding="utf-8")
            lines = text.splitlines()
            for node in ast.walk(ast.parse(text, filename=str(path))):
                if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                    n = _code_lines(node, lines)
                    if n > MAX_CODE_LINES:
                        doc = ast.get_docstring(node) or ""
                        reason = any(line.strip().startswith(LONG_REASON) for line in doc.splitlines())
                        found[f"{path.relative_to(root).as_posix()}:{node.name}"] = (n, reason)
    return found


def test_functions_are_short_or_say_why():
    found = _long_functions(REPO)
    unexplained = sorted(
        f"{name} ({n} code lines)" for name, (n, reason) in found.items() if not reason and name not in ALLOWED_LONG
    )
    assert not unexplained, (
        f"functions over {MAX_CODE_LINES} code lines without a '{LONG_REASON} ...' line in "
        "their docstring (docs/architecture.md):\n" + "\n".join(unexplained)
    )
    stale = sorted(ALLOWED_LONG - {name for name, (_, reason) in found.items() if not reason})
    assert not stale, "no longer long (or now explained): remove from ALLOWED_LONG:\n" + "\n".join(stale)


def test_the_length_check_can_fail(tmp_path):
    (tmp_path / "pkg").mkdir()
    body = "".join(
        f"    x{i} = {i}  # a comment after code counts\n\n    # a comment line does not\n"
        for i in range(MAX_CODE_LINES)
    )
    (tmp_path / "pkg" / "m.py").write_text(
        "def short():\n    '''Docstring lines\n\n    do not count.\n    '''\n"
        + body
        + "def long(\n    a,\n):\n    x = 0\n"
        + body
        + f"def explained():\n    '''Why.\n\n    {LONG_REASON} it is a table.\n    '''\n    x = 0\n"
        + body
    )
    assert _long_functions(tmp_path, ("pkg",)) == {"pkg/m.py:long": (61, False), "pkg/m.py:explained": (61, True)}


# -- named constants are enums ---------------------------------------------------------------------
# Plain classes of int constants that must stay so (none today); each entry fails once it is an enum.
ALLOWED_INT_CLASSES: set[str] = set()


def _bare_int_constants(root: Path, packages=CHECKED) -> list[str]:
    """Module-level ``A, B, C = range(n)`` and classes (not enums) whose body is only int
    constants: both are what :class:`enum.IntEnum` is for."""
    found = []
    for package in packages:
        for path in sorted((root / package).rglob("*.py")):
            where = path.relative_to(root).as_posix()
            tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
            for node in tree.body:
                if (
                    isinstance(node, ast.Assign)
                    and isinstance(node.targets[0], ast.Tuple)
                    and isinstance(node.value, ast.Call)
                    and getattr(node.value.func, "id", "") == "range"
                ):
                    found.append(f"{where}:{node.lineno}")
                elif isinstance(node, ast.ClassDef) and not node.bases:
                    values = [s.value for s in node.body if isinstance(s, ast.Assign)]
                    if len(values) >= 2 and all(isinstance(v, ast.Constant) and type(v.value) is int for v in values):
                        found.append(f"{where}:{node.name}")
    return found


def test_named_int_constants_are_enums():
    found = set(_bare_int_constants(REPO))
    assert not found - ALLOWED_INT_CLASSES, "use enum.IntEnum for:\n" + "\n".join(sorted(found - ALLOWED_INT_CLASSES))
    assert not ALLOWED_INT_CLASSES - found, (
        f"now an enum: remove from ALLOWED_INT_CLASSES: {ALLOWED_INT_CLASSES - found}"
    )


def test_the_enum_check_can_fail(tmp_path):
    (tmp_path / "pkg").mkdir()
    (tmp_path / "pkg" / "m.py").write_text(
        "import enum\nA, B = range(2)\nclass Key:\n    '''Doc.'''\n    X = 0\n    Y = 1\n"
        "class Fine(enum.IntEnum):\n    X = 0\n    Y = 1\nclass Mixed:\n    X = 0\n    name = 'm'\n"
    )
    assert _bare_int_constants(tmp_path, ("pkg",)) == ["pkg/m.py:2", "pkg/m.py:Key"]


# -- a docstring is the first statement ------------------------------------------------------------
def _misplaced_docstrings(root: Path, packages=PACKAGES) -> list[str]:
    """A bare string statement after the first in a function: a docstring placed after code,
    which Python does not take as the docstring (``help()`` and numpydoc never see it)."""
    found = []
    for package in packages:
        for path in sorted((root / package).rglob("*.py")):
            for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), filename=str(path))):
                if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                    found += [
                        f"{path.relative_to(root).as_posix()}:{s.lineno}"
                        for s in node.body[1:]
                        if isinstance(s, ast.Expr)
                        and isinstance(s.value, ast.Constant)
                        and isinstance(s.value.value, str)
                    ]
    return found


def test_docstrings_come_first():
    found = _misplaced_docstrings(REPO)
    assert not found, "a string statement after code (move it up to be the docstring):\n" + "\n".join(found)


def test_the_docstring_check_can_fail(tmp_path):
    (tmp_path / "pkg").mkdir()
    (tmp_path / "pkg" / "m.py").write_text(
        "def f():\n    x = 1\n    '''Late.'''\n    return x\ndef g():\n    '''Fine.'''\n    return 1\n"
    )
    assert _misplaced_docstrings(tmp_path, ("pkg",)) == ["pkg/m.py:3"]


def _direct_tqdm_imports(path: Path) -> list[str]:
    """Imports of tqdm itself (``import tqdm``, ``from tqdm... import``) in ``path``."""
    found = []
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), filename=str(path))):
        modules = [a.name for a in node.names] if isinstance(node, ast.Import) else []
        if isinstance(node, ast.ImportFrom) and node.level == 0:
            modules = [node.module or ""]
        found += [f"{path.relative_to(REPO)}:{node.lineno}: {m}" for m in modules if m.split(".")[0] == "tqdm"]
    return found


def test_progress_bars_come_from_radiokit_progress():
    """A bar made by tqdm directly misses radiokit.progress's width on a terminal reporting 0
    columns (squeezed into one cell, its last character cut): only that module imports tqdm."""
    found = [
        hit
        for package in PACKAGES
        for path in sorted((REPO / package).rglob("*.py"))
        if path != REPO / "radiokit" / "progress.py"
        for hit in _direct_tqdm_imports(path)
    ]
    assert not found, "tqdm imported directly (use radiokit.progress.tqdm):\n" + "\n".join(found)


def test_the_tqdm_check_can_fail(tmp_path):
    (tmp_path / "m.py").write_text("from tqdm.auto import tqdm\nimport tqdm\nfrom radiokit.progress import tqdm\n")
    with _repo_at(tmp_path):
        assert len(_direct_tqdm_imports(tmp_path / "m.py")) == 2


# -- importing a module changes nothing ------------------------------------------------------------
# pytest imports every module of sim/ and acquisition/ to collect their doctests (pyproject's
# testpaths): a handler installed, a logger configured, a file or a thread left by an import would
# change every test after it in that worker. A fresh interpreter imports them all and reports what
# changed, in a scratch folder.
_IMPORT_ALL = """
import importlib, logging, os, pkgutil, signal, sys, threading
sys.path.insert(0, sys.argv[1])
signals = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)
before = ({s: signal.getsignal(s) for s in signals}, set(os.listdir(".")), threading.active_count())
for name in sys.argv[2:]:
    package = importlib.import_module(name)
    for m in pkgutil.walk_packages(package.__path__, name + "."):
        if not m.name.endswith("__main__"):
            importlib.import_module(m.name)
loggers = [n for n, lg in logging.Logger.manager.loggerDict.items() if getattr(lg, "handlers", None)]
changed = {
    "signal handlers": {s: signal.getsignal(s) for s in signals} != before[0],
    "files": sorted(set(os.listdir(".")) - before[1]),
    "threads": threading.active_count() - before[2],
    "root logger": logging.getLogger().handlers or None,
    "loggers with handlers": loggers,
}
print({k: v for k, v in changed.items() if v})
"""


def _import_side_effects(root: Path, packages, cwd: Path) -> str:
    import subprocess
    import sys

    res = subprocess.run(
        [sys.executable, "-c", _IMPORT_ALL, str(root), *packages], cwd=cwd, capture_output=True, text=True, timeout=120
    )
    assert res.returncode == 0, res.stderr
    return res.stdout.strip()


def test_importing_sim_and_acquisition_has_no_side_effects(tmp_path):
    assert _import_side_effects(REPO, ("sim", "acquisition"), tmp_path) == "{}"


def test_the_side_effect_check_can_fail(tmp_path):
    pkg = tmp_path / "src" / "noisy"
    pkg.mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "m.py").write_text(
        "import logging, signal\nlogging.basicConfig()\nsignal.signal(signal.SIGTERM, signal.SIG_IGN)\n"
        "open('left.txt', 'w').close()\n"
    )
    said = _import_side_effects(tmp_path / "src", ("noisy",), tmp_path)
    assert all(k in said for k in ("signal handlers", "left.txt", "root logger")), said
