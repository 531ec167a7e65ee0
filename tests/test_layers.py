"""The packages' layering, read from their sources (every import, at module level or in a function).

From the bottom up: ``rtkit`` (what both sides' processes share) imports none of the
others; ``vespro`` (vision) imports nothing from ``servo`` or ``cellsim``; ``servo``
imports from ``vespro`` only the wire protocol and nothing from ``cellsim``;
``cellsim`` (the simulated cell, driving both sides) sits on top. The one exception:
the ``vespro`` command line hands ``vespro demo`` to ``cellsim`` in the command's
handler, when it runs.

Within the packages, a command module (``vespro/cmd_*.py``, ``cellsim/cmd_demo.py``)
builds its sub-command and runs it; what commands share lives in library modules, so
no module imports a command module but the command-line dispatcher. And no module
imports another's private (``_name``) names; tests and benchmarks may reach into the
module they exercise.
"""

import ast
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("rtkit", "vespro", "servo", "cellsim")

#: package -> (packages it must not import, modules of those it may import all the same)
RULES = {
    "rtkit": ({"vespro", "servo", "cellsim"}, set()),
    "vespro": ({"servo", "cellsim"}, set()),
    "servo": ({"vespro", "cellsim"}, {"vespro.wire"}),
}
#: (file, module): imports allowed in that file only, and only inside a function (lazily).
LAZY_EXCEPTIONS = {("vespro/cli.py", "cellsim.cmd_demo")}


def _in_function(tree: ast.AST) -> set[int]:
    """ids of the nodes inside a function (or lambda) of the tree."""
    inside = set()
    for node in ast.walk(tree):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)):
            inside.update(id(n) for n in ast.walk(node) if n is not node)
    return inside


def _imports(tree: ast.AST) -> list[tuple[str, bool]]:
    """(absolute module imported, inside a function) for every import of the tree; relative
    imports stay in their package and are left out. A literal ``importlib.import_module`` counts."""
    in_function = _in_function(tree)
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0:
            # "from pkg import mod" imports pkg.mod; "from pkg.mod import name" imports pkg.mod
            names = [f"{node.module}.{a.name}" for a in node.names] if node.module in PACKAGES else [node.module]
        elif (isinstance(node, ast.Call) and getattr(node.func, "attr", getattr(node.func, "id", None))
              in ("import_module", "__import__") and node.args and isinstance(node.args[0], ast.Constant)
              and isinstance(node.args[0].value, str)):
            names = [node.args[0].value]
        else:
            continue
        found += [(n, id(node) in in_function) for n in names]
    return found


def test_each_package_imports_only_the_layers_below_it():
    offenders, exceptions_seen, n_files = [], set(), 0
    for package, (forbidden, allowed) in RULES.items():
        files = sorted((ROOT / package).rglob("*.py"))
        assert files, f"{package}/ has no sources"
        n_files += len(files)
        for path in files:
            rel = path.relative_to(ROOT).as_posix()
            for module, lazy in _imports(ast.parse(path.read_text(), rel)):
                if module.split(".")[0] not in forbidden:
                    continue
                if any(module == a or module.startswith(a + ".") for a in allowed):
                    continue
                if (rel, module) in LAZY_EXCEPTIONS and lazy:
                    exceptions_seen.add((rel, module))
                    continue
                offenders.append(f"{rel}: {module}" + (" (at module level)" if not lazy else ""))
    assert n_files > 100
    assert not offenders, "imports against the layering: " + "; ".join(offenders)
    # The exception is the demo's dispatch; when it goes, its entry goes too.
    assert exceptions_seen == LAZY_EXCEPTIONS


#: Command modules: each builds its sub-command and runs it (a module name pattern).
COMMAND_MODULE = re.compile(r"(vespro\.cmd_\w+|servo\.cmd_\w+|cellsim\.cmd_demo)(\.|$)")
#: The command-line dispatcher, which may import the command modules (lazily only).
DISPATCHER = "vespro/cli.py"


def _sources(*dirs: str) -> list[tuple[str, ast.AST]]:
    """(path relative to the root, parsed tree) of every source under the folders."""
    out = []
    for d in dirs:
        for path in sorted((ROOT / d).rglob("*.py")):
            rel = path.relative_to(ROOT).as_posix()
            out.append((rel, ast.parse(path.read_text(), rel)))
    return out


def _from_imports(rel: str, tree: ast.AST) -> list[tuple[str, list[str], bool, int]]:
    """(absolute module, names imported from it, inside a function, line) for every import of
    the tree, relative ones resolved against the file's package; ``import a.b`` gives ("a.b", [])."""
    in_function = _in_function(tree)
    package = rel[:-3].split("/")[:-1]
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found += [(a.name, [], id(node) in in_function, node.lineno) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = package[:len(package) - node.level + 1] if node.level else []
            module = ".".join([*base, *([node.module] if node.module else [])])
            found.append((module, [a.name for a in node.names], id(node) in in_function, node.lineno))
    return found


def test_no_module_imports_a_command_module():
    offenders, dispatched, files = [], set(), _sources(*PACKAGES, "bench")
    assert len(files) > 100
    for rel, tree in files:
        for module, names, lazy, line in _from_imports(rel, tree):
            # "from vespro import cmd_track" imports the command module too
            hits = {h.group(1) for m in (module, *(f"{module}.{n}" for n in names))
                    if (h := COMMAND_MODULE.match(m))}
            if not hits:
                continue
            if rel == DISPATCHER and lazy:
                dispatched |= hits
                continue
            offenders += [f"{rel}:{line}: {m}" for m in sorted(hits)]
    assert not offenders, "command modules imported (move what they share to a library module): " + "; ".join(
        offenders)
    assert "cellsim.cmd_demo" in dispatched  # the check sees the dispatcher's own (lazy) import


def test_no_module_imports_a_private_name_of_another():
    offenders, n_from = [], 0
    for rel, tree in _sources(*PACKAGES):
        for module, names, _, line in _from_imports(rel, tree):
            if module.split(".")[0] not in PACKAGES:
                continue
            n_from += 1
            private = [n for n in names if n.startswith("_") and not (n.startswith("__") and n.endswith("__"))]
            offenders += [f"{rel}:{line}: {module}.{n}" for n in private]
    assert n_from > 300
    assert not offenders, "private names imported from another module (make them public): " + "; ".join(offenders)


def test_the_tracker_loads_no_hypothesis_search():
    """The tracker measures poses on image edges (:mod:`vespro.edgefit`) and reads the
    initialiser's camera and model helpers; the initialiser itself (its hypothesis search)
    loads only where one is made. Imported first, the edge measurement loads too (the
    search imports it, and it imports those helpers)."""
    import os
    import subprocess
    import sys

    code = ("import sys, vespro.edgefit, vespro.tracker; "
            "print(' '.join(sorted(m for m in sys.modules if m.startswith('vespro.init'))))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                         env={**os.environ, "PYTHONPATH": str(ROOT)}, cwd=ROOT).stdout.split()
    assert "vespro.init.features" in out and "vespro.init.modelfeat" in out
    assert "vespro.init.search" not in out and "vespro.init.initializer" not in out
