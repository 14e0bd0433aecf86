"""Who may call which route: each routes module declares ``ACCESS = {"METHOD /path": level}``
next to its routes; :func:`table` merges them (``tests/app/test_security.py`` walks every
operation of the OpenAPI schema against it, so a route without an entry fails the test).

Levels:

=============  ================================================================================
``public``     anyone, no login (login, health)
``user``       any logged-in user (own account, own sessions)
``member``     any role, but annotators and reviewers only for scenes they are members of
``annotator``  annotators who are members of the scene, and admins
``reviewer``   reviewers who are members of the scene, and admins
``staff``      reviewers and admins, not scoped to one scene (the job list filters by membership)
``admin``      admins only
=============  ================================================================================
"""

from __future__ import annotations

from app.annotations import confidence, smart
from app.annotations import routes as annotations
from app.audit import routes as audit
from app.corrections import routes as corrections
from app.jobs import archive
from app.jobs import routes as jobs
from app.lifting import routes as lifting
from app.notifications import routes as notifications
from app.review import routes as review
from app.scenes import console, imports
from app.scenes import routes as scenes
from app.users import routes as users

LEVELS = ("public", "user", "member", "annotator", "reviewer", "staff", "admin")

# the app's own routes (app/main.py)
ACCESS = {"GET /api/health": "public"}


def table() -> dict[str, str]:
    merged: dict[str, str] = dict(ACCESS)
    for mod in (users, scenes, annotations, confidence, smart, review, jobs, archive, audit,
                corrections, notifications, imports, console, lifting):
        for key, level in getattr(mod, "ACCESS", {}).items():
            if level not in LEVELS:
                raise ValueError(f"{mod.__name__}.ACCESS[{key!r}]: unknown level {level!r}")
            if key in merged:
                raise ValueError(f"{key} is declared twice ({mod.__name__})")
            merged[key] = level
    return merged


def allowed(level: str, role: str | None, member: bool) -> bool:
    """Whether a caller (role None = anonymous) may use a route of ``level``."""
    if level == "public":
        return True
    if role is None:
        return False
    if role == "admin" or level == "user":
        return True
    if level == "admin":
        return False
    if level == "staff":
        return role == "reviewer"
    if not member:
        return False
    return level == "member" or level == role
