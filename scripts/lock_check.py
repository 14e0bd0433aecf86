"""Does the environment satisfy pyproject.toml, and does requirements.lock pin everything it
names? ``python scripts/lock_check.py [EXTRAS]`` (comma-separated, e.g. ``dev,masks``) prints
each requirement that is missing from the lock or not installed at an allowed version, and
exits 1 if there is one (scripts/setup.sh, tests/test_lock.py)."""

from __future__ import annotations

import re
import sys
import tomllib
from importlib import metadata
from pathlib import Path

from packaging.requirements import Requirement

REPO = Path(__file__).resolve().parent.parent


def _norm(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def pins(*paths: Path) -> dict[str, str]:
    out = {}
    for p in paths:
        if p.is_file():
            for m in re.finditer(r"^([A-Za-z0-9_.-]+)==([^\s\\;]+)", p.read_text(), flags=re.M):
                out[_norm(m.group(1))] = m.group(2)
    return out


def problems(extras: list[str]) -> list[str]:
    proj = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]
    reqs = [Requirement(r) for r in proj["dependencies"]]
    for e in extras:
        reqs += [Requirement(r) for r in proj.get("optional-dependencies", {}).get(e, [])]
    locked = pins(REPO / "requirements.lock", REPO / "requirements-torch.lock")
    out = []
    for r in reqs:
        if r.marker is not None and not r.marker.evaluate():
            continue
        name = _norm(r.name)
        if name not in locked:
            out.append(f"{r}: not pinned in requirements.lock (run scripts/lock.sh)")
        elif not r.specifier.contains(locked[name].split("+")[0], prereleases=True):
            out.append(f"{r}: requirements.lock pins {locked[name]}, outside the range")
        try:
            have = metadata.version(r.name)
        except metadata.PackageNotFoundError:
            out.append(f"{r}: not installed")
            continue
        if not r.specifier.contains(have.split("+")[0], prereleases=True):
            out.append(f"{r}: {have} installed")
    return out


if __name__ == "__main__":
    extras = [e for e in (sys.argv[1] if len(sys.argv) > 1 else "").split(",") if e]
    found = problems(extras)
    for p in found:
        print(f"lock: {p}", file=sys.stderr)
    sys.exit(1 if found else 0)
