"""The packages' layering, read from their sources (every import, at module level or in a function).

From the bottom up: ``rtkit`` (what both sides' processes share) imports none of the
others; ``vespro`` (vision) imports nothing from ``servo`` or ``cellsim``; ``servo``
imports from ``vespro`` only the wire protocol and nothing from ``cellsim``;
``cellsim`` (the simulated cell, driving both sides) sits on top. The one exception:
the ``vespro`` command line hands ``vespro demo`` to ``cellsim`` in the command's
handler, when it runs.
"""

import ast
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


def _imports(tree: ast.AST) -> list[tuple[str, bool]]:
    """(absolute module imported, inside a function) for every import of the tree; relative
    imports stay in their package and are left out. A literal ``importlib.import_module`` counts."""
    in_function = set()
    for node in ast.walk(tree):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)):
            in_function.update(id(n) for n in ast.walk(node) if n is not node)
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
