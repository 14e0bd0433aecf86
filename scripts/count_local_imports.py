"""Count imports inside functions (``def`` bodies) per package: the architecture check's
"function-level imports" figure. ``python scripts/count_local_imports.py occufly app [-v]``
prints ``<package>: N`` (and, with -v, each one with the module it imports)."""

from __future__ import annotations

import ast
import sys
from pathlib import Path


def local_imports(path: Path) -> list[tuple[int, str]]:
    tree = ast.parse(path.read_text(), filename=str(path))
    out: list[tuple[int, str]] = []

    def visit(node: ast.AST, in_func: bool) -> None:
        for child in ast.iter_child_nodes(node):
            f = in_func or isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda))
            if in_func and isinstance(child, ast.Import):
                out.extend((child.lineno, a.name) for a in child.names)
            elif in_func and isinstance(child, ast.ImportFrom):
                mod = "." * child.level + (child.module or "")
                out.append((child.lineno, mod))
            visit(child, f)

    visit(tree, False)
    return out


def main(argv: list[str]) -> int:
    verbose = "-v" in argv
    for pkg in [a for a in argv if a != "-v"]:
        total = 0
        for p in sorted(Path(pkg).rglob("*.py")):
            found = local_imports(p)
            total += len(found)
            if verbose:
                for line, mod in found:
                    print(f"{p}:{line}: {mod}")
        print(f"{pkg}: {total}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
