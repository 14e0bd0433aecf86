"""The import layers written down in ``pyproject.toml`` ([tool.importlinter]) hold:
``lint-imports`` checks every import, those inside functions included."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent


def test_import_contracts_hold():
    exe = Path(sys.executable).parent / "lint-imports"
    r = subprocess.run([str(exe), "--no-cache"], cwd=REPO, capture_output=True, text=True,
                       timeout=300)
    assert r.returncode == 0, r.stdout[-6000:] + r.stderr[-2000:]
    assert "BROKEN" not in r.stdout and r.stdout.count("KEPT") >= 5


# ---- no circle anywhere (issue 35) ------------------------------------------------------------
def _import_graph():
    import grimp

    return grimp.build_graph("app", "occufly", include_external_packages=False,
                             exclude_type_checking_imports=False, cache_dir=None)


def _circles(graph) -> list[list[str]]:  # noqa: ANN001
    """The import circles (strongly connected components of more than one module) of
    ``graph``, Tarjan's algorithm without recursion."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    on_stack: set[str] = set()
    stack: list[str] = []
    out: list[list[str]] = []
    counter = 0
    for root in sorted(graph.modules):
        if root in index:
            continue
        work = [(root, iter(sorted(graph.find_modules_directly_imported_by(root))))]
        index[root] = low[root] = counter
        counter += 1
        stack.append(root)
        on_stack.add(root)
        while work:
            node, children = work[-1]
            for child in children:
                if child not in index:
                    index[child] = low[child] = counter
                    counter += 1
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(graph.find_modules_directly_imported_by(child)))))
                    break
                if child in on_stack:
                    low[node] = min(low[node], index[child])
            else:
                work.pop()
                if work:
                    low[work[-1][0]] = min(low[work[-1][0]], low[node])
                if low[node] == index[node]:
                    comp = []
                    while True:
                        m = stack.pop()
                        on_stack.discard(m)
                        comp.append(m)
                        if m == node:
                            break
                    if len(comp) > 1:
                        out.append(sorted(comp))
    return out


def test_no_import_circle_anywhere_in_app_or_library():
    """Every import counts (inside functions, under TYPE_CHECKING): a circle of any length
    between any modules of app/ or occufly/ fails, naming its modules."""
    circles = _circles(_import_graph())
    assert circles == [], "import circles:\n" + "\n".join(" -> ".join(c) for c in circles)


def test_a_re_added_circle_is_caught_by_the_graph_check_and_the_contracts(tmp_path):
    """The check is not vacuous: the import that tied the app's circle (the context naming
    the concrete job runner) put back into a copy of the tree breaks lint-imports' contracts
    and shows as a circle."""
    import shutil

    graph = _import_graph()
    graph.add_import(importer="app.context", imported="app.jobs.runner")
    assert any("app.context" in c and "app.jobs.runner" in c for c in _circles(graph))

    for name in ("app", "occufly"):
        shutil.copytree(REPO / name, tmp_path / name,
                        ignore=shutil.ignore_patterns("__pycache__", "*.pyc", "*.so"))
    shutil.copy(REPO / "pyproject.toml", tmp_path / "pyproject.toml")
    ctx_py = tmp_path / "app" / "context.py"
    ctx_py.write_text(ctx_py.read_text().replace(
        "from app.config import Settings\n",
        "from app.config import Settings\nfrom app.jobs.runner import JobRunner  # noqa: F401\n"))
    exe = Path(sys.executable).parent / "lint-imports"
    r = subprocess.run([str(exe), "--no-cache"], cwd=tmp_path, capture_output=True, text=True,
                       timeout=300, env={"PYTHONPATH": str(tmp_path), "PATH": "/usr/bin:/bin"})
    assert r.returncode != 0, r.stdout[-3000:]
    assert "BROKEN" in r.stdout and "app.context is not allowed to import app.jobs.runner" in r.stdout.replace("\n", " ")


def test_no_function_over_120_lines():
    """A newcomer can hold any function of app/ or occufly/ in their head (issue 35)."""
    import ast

    long = []
    for pkg in ("app", "occufly"):
        for p in sorted((REPO / pkg).rglob("*.py")):
            for node in ast.walk(ast.parse(p.read_text())):
                if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                    n = node.end_lineno - node.lineno + 1
                    if n > 120:
                        long.append(f"{p.relative_to(REPO)}:{node.lineno} {node.name} ({n} lines)")
    assert long == [], "functions over 120 lines:\n" + "\n".join(long)


def test_every_function_level_import_in_the_app_says_why():
    """An import inside a function is for a heavy or optional dependency, never to get around
    a circle (issue 35): each one in app/ carries its reason as a comment on its line."""
    import ast

    bare = []
    for p in sorted((REPO / "app").rglob("*.py")):
        src = p.read_text()
        lines = src.split("\n")
        seen = set()
        for node in ast.walk(ast.parse(src)):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                for sub in ast.walk(node):
                    if isinstance(sub, (ast.Import, ast.ImportFrom)) and sub.lineno not in seen:
                        seen.add(sub.lineno)
                        if "#" not in lines[sub.lineno - 1]:
                            bare.append(f"{p.relative_to(REPO)}:{sub.lineno}: {lines[sub.lineno - 1].strip()}")
    assert bare == [], "function-level imports without a reason:\n" + "\n".join(bare)
