"""Users, login sessions and login throttling."""

from __future__ import annotations

from datetime import timedelta

from sqlalchemy import delete, select
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from app import security
from app.config import Settings
from app.db import utcnow
from app.errors import Conflict, Invalid, NotAuthenticated, TooManyAttempts
from app.users.models import ROLES, AuthToken, LoginThrottle, User


def create_user(*, session: Session, username: str, password: str, role: str) -> User:
    if role not in ROLES:
        raise Invalid(f"role must be one of {', '.join(ROLES)}, got {role!r}")
    if len(password) < 8:
        raise Invalid("password must have at least 8 characters")
    user = User(username=username, password_hash=security.hash_password(password), role=role)
    session.add(user)
    try:
        session.commit()
    except IntegrityError:
        session.rollback()
        raise Conflict(f"user {username!r} already exists") from None
    return user


def list_users(*, session: Session) -> list[User]:
    return list(session.scalars(select(User).order_by(User.id)))


def get_by_name(*, session: Session, username: str) -> User | None:
    return session.scalar(select(User).where(User.username == username))


def _check_throttle(session: Session, keys: list[str]) -> None:
    now = utcnow()
    for key in keys:
        row = session.get(LoginThrottle, key)
        if row is not None and row.locked_until is not None and row.locked_until > now:
            wait = max(1, int((row.locked_until - now).total_seconds() + 0.999))
            raise TooManyAttempts(
                f"too many failed logins; try again in {wait} s", retry_after=wait)


def _record_failure(session: Session, settings: Settings, keys: list[str]) -> None:
    now = utcnow()
    for key in keys:
        row = session.get(LoginThrottle, key)
        if row is None:
            row = LoginThrottle(key=key, failures=0)
            session.add(row)
        row.failures += 1
        row.updated_at = now
        # an address (office NAT) is shared by many people: it gets 4x the free failures
        free = settings.login_free_failures * (4 if key.startswith("ip:") else 1)
        lock = security.lock_duration(row.failures, free, settings.login_max_lock_s)
        row.locked_until = now + lock if lock else None
    try:
        session.commit()
    except IntegrityError:  # a concurrent failure created the row first; its count is enough
        session.rollback()


def login(*, session: Session, settings: Settings, username: str, password: str,
          client_ip: str) -> tuple[User, str]:
    """Check credentials; returns (user, token). Failures count per user name and per IP."""
    keys = [f"user:{username.lower()}"[:128], f"ip:{client_ip}"[:128]]
    _check_throttle(session, keys)
    user = get_by_name(session=session, username=username)
    ok = security.verify_password(user.password_hash if user else None, password)
    if not ok or user is None or not user.active:
        _record_failure(session, settings, keys)
        raise NotAuthenticated("wrong user name or password")
    session.execute(delete(LoginThrottle).where(LoginThrottle.key == keys[0]))
    token = security.new_token()
    session.add(AuthToken(user_id=user.id, token_hash=security.token_digest(settings.secret_key, token),
                          expires_at=utcnow() + timedelta(seconds=settings.session_seconds)))
    session.commit()
    return user, token


def logout(*, session: Session, settings: Settings, token: str) -> None:
    session.execute(delete(AuthToken).where(
        AuthToken.token_hash == security.token_digest(settings.secret_key, token)))
    session.commit()


def user_for_token(*, session: Session, settings: Settings, token: str) -> User | None:
    row = session.scalar(select(AuthToken).where(
        AuthToken.token_hash == security.token_digest(settings.secret_key, token)))
    if row is None or row.expires_at < utcnow():
        return None
    user = session.get(User, row.user_id)
    return user if user is not None and user.active else None


def issue_token(*, session: Session, settings: Settings, user: User) -> str:
    """A token for scripts/tests without a password round trip."""
    token = security.new_token()
    session.add(AuthToken(user_id=user.id, token_hash=security.token_digest(settings.secret_key, token),
                          expires_at=utcnow() + timedelta(seconds=settings.session_seconds)))
    session.commit()
    return token
