"""Users, login sessions, login throttling and account administration.

Throttling keys (see :class:`app.users.models.LoginThrottle`): a failure counts for the pair
(account, address), the address and the account. The pair locks after ``login_free_failures``
failures (exponential, capped at ``login_max_lock_s``); the address after 4x that (password
spraying), but an account that has logged in from that address before is not locked out by
it; the account alone after ``login_user_free_factor`` x the free failures, with a short cap
(``login_user_max_lock_s``) so that nobody can keep a named account locked. Admins unlock an
account (every key naming it) with ``POST /api/users/{id}/unlock``.
"""

from __future__ import annotations

import functools
import gzip
from datetime import timedelta
from pathlib import Path

from sqlalchemy import case, delete, func, or_, select, update
from sqlalchemy.dialects import postgresql, sqlite
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from app import credentials as security  # hashing and tokens (app.security builds on this)
from app.config import Settings
from app.db import utcnow
from app.errors import Conflict, Forbidden, Invalid, NotAuthenticated, NotFound, TooManyAttempts
from app.users.models import ROLES, AuthToken, LoginThrottle, User

MIN_PASSWORD = 8
#: 19,640 passwords most often found in breaches (the list Django ships in
#: django/contrib/auth/common-passwords.txt.gz, BSD licence: docs/security.md), bundled so the
#: check needs no network; compared lower-cased
COMMON_PASSWORDS_FILE = Path(__file__).with_name("common-passwords.txt.gz")


@functools.lru_cache(maxsize=1)
def common_passwords() -> frozenset[str]:
    with gzip.open(COMMON_PASSWORDS_FILE, "rt", encoding="utf-8") as f:
        return frozenset(line.strip().lower() for line in f if line.strip())


def _check_password(password: str, username: str | None = None) -> None:
    """The password policy (issue 24): at least MIN_PASSWORD characters, not one character
    repeated, not in the common-password list, and not the user name (nor the user name with
    fewer than four other characters, e.g. ``admin123``). 422 saying which rule failed."""
    if len(password) < MIN_PASSWORD:
        raise Invalid(f"password must have at least {MIN_PASSWORD} characters")
    low = password.lower()
    if len(set(low)) < 3:
        raise Invalid("password is too simple: it uses fewer than three different characters")
    if low in common_passwords():
        raise Invalid("password is one of the most common passwords (it appears in breach "
                      "lists); choose another")
    if username:
        name = username.lower()
        if low == name or (name in low and len(low) - len(name) < 4) or low in name:
            raise Invalid("password must not be the user name or the user name with a few "
                          "characters added")


def create_user(*, session: Session, username: str, password: str, role: str) -> User:
    if role not in ROLES:
        raise Invalid(f"role must be one of {', '.join(ROLES)}, got {role!r}")
    _check_password(password, username)
    if get_by_name(session=session, username=username) is not None:
        raise Conflict(f"user {username!r} already exists (user names are case-insensitive)")
    user = User(username=username, password_hash=security.hash_password(password), role=role)
    session.add(user)
    try:
        session.commit()
    except IntegrityError:
        session.rollback()
        raise Conflict(f"user {username!r} already exists (user names are case-insensitive)") from None
    return user


def list_users(*, session: Session) -> list[User]:
    return list(session.scalars(select(User).order_by(User.id)))


def get_by_name(*, session: Session, username: str) -> User | None:
    """The user of that name, ignoring case."""
    return session.scalar(select(User).where(func.lower(User.username) == username.lower()))


def get_user(*, session: Session, user_id: int) -> User:
    user = session.get(User, user_id)
    if user is None:
        raise NotFound(f"user {user_id} does not exist")
    return user


# ---- throttling -----------------------------------------------------------------------------
def _keys(username: str, client_ip: str) -> dict[str, str]:
    name = username.lower()[:64]
    ip = client_ip[:64]
    return {"pair": f"pair:{name}@{ip}"[:128], "ip": f"ip:{ip}"[:128],
            "user": f"user:{name}"[:128], "ok": f"ok:{name}@{ip}"[:128]}


def _limits(settings: Settings) -> dict[str, tuple[int, int]]:
    free = settings.login_free_failures
    return {"pair": (free, settings.login_max_lock_s),
            "ip": (4 * free, settings.login_max_lock_s),  # an office NAT is shared by many
            "user": (settings.login_user_free_factor * free,
                     min(settings.login_user_max_lock_s, settings.login_max_lock_s))}


def _reserve_attempt(session: Session, settings: Settings, keys: dict[str, str]) -> None:
    """Count this attempt as a failure of every key *before* the password is verified, in one
    transaction, each key's count incremented atomically (``INSERT .. ON CONFLICT DO UPDATE
    .. WHERE not locked``: the row lock on PostgreSQL, the write lock on SQLite, serialise
    parallel attempts, and the WHERE sees the lock the previous one set). An attempt that
    finds a checked key locked counts nowhere and raises 429; so of parallel wrong
    passwords at most the free failures of a key are verified (issue 36: before, all of
    them passed the check before the first failure was recorded). A success takes its count
    back (:func:`login`)."""
    now = utcnow()
    insert = postgresql.insert if session.get_bind().dialect.name == "postgresql" else sqlite.insert
    check_ip = session.get(LoginThrottle, keys["ok"]) is None  # a known account passes a
    limits = _limits(settings)                                  # locked address
    t = LoginThrottle.__table__
    for kind in ("pair", "user", "ip"):
        key = keys[kind]
        n_free, cap = limits[kind]
        stmt = insert(t).values(key=key, failures=1, locked_until=None, updated_at=now)
        not_locked = (t.c.locked_until.is_(None)) | (t.c.locked_until <= now)
        stmt = stmt.on_conflict_do_update(
            index_elements=[t.c.key],
            set_={"failures": t.c.failures + 1, "updated_at": now},
            where=not_locked if (kind != "ip" or check_ip) else None,
        ).returning(t.c.failures)
        failures = session.scalar(stmt)
        if failures is None:  # locked: nothing of this attempt is counted
            until = session.scalar(select(LoginThrottle.locked_until)
                                   .where(LoginThrottle.key == key))
            session.rollback()
            wait = max(1, int(((until or now) - now).total_seconds() + 0.999))
            raise TooManyAttempts(f"too many failed logins; try again in {wait} s",
                                  retry_after=wait)
        lock = security.lock_duration(int(failures), n_free, cap)
        if lock:  # the row is ours until the commit: set the lock the next attempt sees
            session.execute(update(LoginThrottle).where(LoginThrottle.key == key)
                            .values(locked_until=now + lock)
                            .execution_options(synchronize_session=False))
    session.commit()


def login(*, session: Session, settings: Settings, username: str, password: str,
          client_ip: str, user_agent: str | None = None) -> tuple[User, str]:
    """Check credentials; returns (user, token). Failures count per pair, address and account."""
    keys = _keys(username, client_ip)
    _reserve_attempt(session, settings, keys)  # counted as a failure until it succeeds
    user = get_by_name(session=session, username=username)
    ok = security.verify_password(user.password_hash if user else None, password)
    if not ok or user is None or not user.active:
        raise NotAuthenticated("wrong user name or password")
    session.execute(delete(LoginThrottle).where(LoginThrottle.key.in_((keys["pair"], keys["user"]))))
    # the address's count takes this attempt back (a success is no failure of the address)
    ip_free = _limits(settings)["ip"][0]
    session.execute(update(LoginThrottle).where(LoginThrottle.key == keys["ip"],
                                                LoginThrottle.failures > 0)
                    .values(failures=LoginThrottle.failures - 1,
                            locked_until=case((LoginThrottle.failures - 1 < ip_free, None),
                                              else_=LoginThrottle.locked_until))
                    .execution_options(synchronize_session=False))
    if session.get(LoginThrottle, keys["ok"]) is None:
        session.add(LoginThrottle(key=keys["ok"], failures=0, updated_at=utcnow()))
    token = _new_session(session, settings, user, client_ip=client_ip, user_agent=user_agent)
    try:
        session.commit()
    except IntegrityError:  # a concurrent login of the same pair wrote the 'ok' row first
        session.rollback()
        token = _new_session(session, settings, user, client_ip=client_ip, user_agent=user_agent)
        session.commit()
    return user, token


def _new_session(session: Session, settings: Settings, user: User, *, client_ip: str | None,
                 user_agent: str | None) -> str:
    token = security.new_token()
    now = utcnow()
    session.add(AuthToken(user_id=user.id, token_hash=security.token_digest(settings.secret_key, token),
                          created_at=now, expires_at=now + timedelta(seconds=settings.session_seconds),
                          client_ip=(client_ip or None) and client_ip[:64],
                          user_agent=(user_agent or None) and user_agent[:256], last_seen_at=now))
    return token


def unlock(*, session: Session, user: User) -> int:
    """Remove every throttling lock that names the account; returns how many were removed."""
    name = user.username.lower()
    res = session.execute(delete(LoginThrottle).where(or_(
        LoginThrottle.key == f"user:{name}", LoginThrottle.key.like(f"pair:{name}@%"))))
    session.commit()
    return int(res.rowcount or 0)


# ---- sessions -------------------------------------------------------------------------------
def logout(*, session: Session, settings: Settings, token: str) -> None:
    session.execute(delete(AuthToken).where(
        AuthToken.token_hash == security.token_digest(settings.secret_key, token)))
    session.commit()


SEEN_EVERY_S = 60  # last_seen_at is refreshed at most once a minute per session


def user_for_token(*, session: Session, settings: Settings, token: str) -> User | None:
    row = session_for_token(session=session, settings=settings, token=token)
    if row is None:
        return None
    user = session.get(User, row.user_id)
    return user if user is not None and user.active else None


def session_for_token(*, session: Session, settings: Settings, token: str) -> AuthToken | None:
    row = session.scalar(select(AuthToken).where(
        AuthToken.token_hash == security.token_digest(settings.secret_key, token)))
    if row is None:
        return None
    now = utcnow()
    if row.expires_at < now:
        return None
    if row.last_seen_at is None or (now - row.last_seen_at).total_seconds() > SEEN_EVERY_S:
        session.execute(update(AuthToken).where(AuthToken.id == row.id).values(last_seen_at=now))
        session.commit()
    return row


def issue_token(*, session: Session, settings: Settings, user: User) -> str:
    """A token for scripts/tests without a password round trip."""
    token = _new_session(session, settings, user, client_ip=None, user_agent=None)
    session.commit()
    return token


def list_sessions(*, session: Session, user_id: int) -> list[AuthToken]:
    return list(session.scalars(select(AuthToken).where(
        AuthToken.user_id == user_id, AuthToken.expires_at >= utcnow()).order_by(AuthToken.id)))


def revoke_session(*, session: Session, user_id: int, session_id: int) -> None:
    res = session.execute(delete(AuthToken).where(AuthToken.id == session_id,
                                                  AuthToken.user_id == user_id))
    session.commit()
    if res.rowcount != 1:
        raise NotFound(f"user {user_id} has no session {session_id}")


def revoke_all(*, session: Session, user_id: int, keep_id: int | None = None) -> int:
    q = delete(AuthToken).where(AuthToken.user_id == user_id)
    if keep_id is not None:
        q = q.where(AuthToken.id != keep_id)
    res = session.execute(q)
    session.commit()
    return int(res.rowcount or 0)


# ---- account administration -----------------------------------------------------------------
def change_password(*, session: Session, user: User, current: str, new: str,
                    keep_session_id: int | None) -> int:
    """The user's own change: needs the current password; ends every other session."""
    if not security.verify_password(user.password_hash, current):
        raise Forbidden("the current password is wrong")
    _check_password(new, user.username)
    user.password_hash = security.hash_password(new)
    session.commit()
    return revoke_all(session=session, user_id=user.id, keep_id=keep_session_id)


def reset_password(*, session: Session, user: User, new: str) -> int:
    """An admin's reset: ends every session of the user (they log in with the new one)."""
    _check_password(new, user.username)
    user.password_hash = security.hash_password(new)
    session.commit()
    return revoke_all(session=session, user_id=user.id)


def update_user(*, session: Session, actor: User, user: User, role: str | None = None,
                active: bool | None = None) -> dict:
    """Change role and/or active flag. Deactivation revokes every session at once; an admin
    cannot demote or deactivate themself (there must stay someone who can undo it)."""
    changes: dict = {}
    if user.id == actor.id and ((role is not None and role != user.role) or active is False):
        raise Conflict("you cannot demote or deactivate your own account; ask another admin")
    if role is not None and role != user.role:
        if role not in ROLES:
            raise Invalid(f"role must be one of {', '.join(ROLES)}, got {role!r}")
        changes["role"] = [user.role, role]
        user.role = role
    if active is not None and active != user.active:
        changes["active"] = [user.active, active]
        user.active = active
    session.commit()
    if active is False:
        changes["sessions_revoked"] = revoke_all(session=session, user_id=user.id)
    return changes
