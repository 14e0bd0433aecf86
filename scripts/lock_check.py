"""Does the environment satisfy pyproject.toml, and does requirements.lock pin everything it
names? ``python scripts/lock_check.py [EXTRAS]`` (comma-separated, e.g. ``dev,masks``) prints
each requirement that is missing from the lock or not installed at an allowed version, and
exits 1 if there is one (scripts/setup.sh, tests/test_lock.py).

``python scripts/lock_check.py --write-extras LOCK...`` (scripts/lock.sh) writes each pin as
``name[extra,...]==version`` where a locked package asks for it with extras (pip-audit needs
``CacheControl[filecache]``). pip --require-hashes checks an extras requirement on its own: left
as a bare ``cachecontrol==0.14.4`` pin, pip fetched the newest CacheControl for the extra and
refused it as unpinned the day 0.15.0 was published, and setup failed.
"""

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


# a pin line: name, optional [extras], ==version
PIN = re.compile(r"^([A-Za-z0-9_.-]+)(?:\[([A-Za-z0-9_.,-]*)\])?==([^\s\\;]+)", flags=re.M)


def _pin_lines(paths: tuple[Path, ...]):  # noqa: ANN202
    for p in paths:
        if p.is_file():
            yield from PIN.finditer(p.read_text())


def pins(*paths: Path) -> dict[str, str]:
    return {_norm(m.group(1)): m.group(3) for m in _pin_lines(paths)}


def pinned_extras(*paths: Path) -> dict[str, set[str]]:
    """The extras each pin line names (``name[a,b]==v`` -> {a, b})."""
    return {_norm(m.group(1)): {_norm(e) for e in (m.group(2) or "").split(",") if e}
            for m in _pin_lines(paths)}


def _project_requirements(extras: list[str]) -> list[Requirement]:
    proj = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]
    reqs = [Requirement(r) for r in proj["dependencies"]]
    for e in extras:
        reqs += [Requirement(r) for r in proj.get("optional-dependencies", {}).get(e, [])]
    return [r for r in reqs if r.marker is None or r.marker.evaluate({"extra": ""})]


def requested_extras(locked: set[str], extras: list[str]) -> dict[str, set[str]]:
    """For each locked package, the extras some locked package (or pyproject.toml with
    ``extras``) asks it for, read from the installed metadata: a package installed with an
    extra may ask others for extras in turn, so this runs to a fixed point."""
    want: dict[str, set[str]] = {}
    for r in _project_requirements(extras):
        if _norm(r.name) in locked and r.extras:
            want.setdefault(_norm(r.name), set()).update(_norm(e) for e in r.extras)
    changed = True
    while changed:
        changed = False
        for name in sorted(locked):
            try:
                requires = metadata.requires(name) or []
            except metadata.PackageNotFoundError:
                continue
            active = [""] + sorted(want.get(name, ()))
            for text in requires:
                r = Requirement(text)
                dep = _norm(r.name)
                if dep not in locked or not r.extras:
                    continue
                if r.marker is not None and not any(
                    r.marker.evaluate({"extra": e}) for e in active
                ):
                    continue
                new = {_norm(e) for e in r.extras} - want.get(dep, set())
                if new:
                    want.setdefault(dep, set()).update(new)
                    changed = True
    return want


def write_extras(paths: list[Path], extras: list[str]) -> list[str]:
    """Rewrite the pin lines of ``paths`` to carry the requested extras; returns the changed
    names. Every extra's own requirements must already be pinned (uv resolved them)."""
    locked = set(pins(*paths))
    want = requested_extras(locked, extras)
    changed = []
    for p in paths:
        if not p.is_file():
            continue

        def line(m: re.Match) -> str:
            name = _norm(m.group(1))
            if name not in want:
                return m.group(0)
            changed.append(name)
            return f"{m.group(1)}[{','.join(sorted(want[name]))}]=={m.group(3)}"

        p.write_text(PIN.sub(line, p.read_text()))
    return changed


LOCKS = (REPO / "requirements.lock", REPO / "requirements-torch.lock")


def problems(extras: list[str], locks: tuple[Path, ...] = LOCKS) -> list[str]:
    locked = pins(*locks)
    out = []
    have_extras = pinned_extras(*locks)
    for name, wanted in sorted(requested_extras(set(locked), extras).items()):
        if not wanted <= have_extras.get(name, set()):
            out.append(
                f"{name}[{','.join(sorted(wanted))}]: the lock pins it without these extras "
                "(pip --require-hashes then looks up an unpinned version; run scripts/lock.sh)"
            )
    for r in _project_requirements(extras):
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
    if sys.argv[1:2] == ["--write-extras"]:
        names = write_extras([Path(a) for a in sys.argv[2:]], ["dev", "masks", "torch"])
        print(
            f"lock: extras written for {', '.join(sorted(set(names))) or 'no pin'}", file=sys.stderr
        )
        sys.exit(0)
    extras = [e for e in (sys.argv[1] if len(sys.argv) > 1 else "").split(",") if e]
    found = problems(extras)
    for p in found:
        print(f"lock: {p}", file=sys.stderr)
    sys.exit(1 if found else 0)
