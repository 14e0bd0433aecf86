"""Credentials: password hashing (argon2id), session tokens and their keyed digests, the
login lock-out schedule. The bottom of the app's security: the users service and the request
checks in :mod:`app.security` build on it (it imports nothing of the app)."""

from __future__ import annotations

import hashlib
import hmac
import secrets
from datetime import timedelta

from argon2 import PasswordHasher
from argon2.exceptions import InvalidHashError, VerificationError, VerifyMismatchError

_hasher = PasswordHasher()  # argon2id with the library's current recommended parameters
# verifying against this keeps the time of "unknown user" equal to "wrong password"
_DUMMY_HASH = _hasher.hash("not-a-real-password-0")


def configure(*, time_cost: int, memory_kib: int) -> None:
    """Set the argon2id cost for new hashes (existing hashes carry their own parameters)."""
    global _hasher, _DUMMY_HASH
    if (_hasher.time_cost, _hasher.memory_cost) == (time_cost, memory_kib):
        return
    _hasher = PasswordHasher(time_cost=time_cost, memory_cost=memory_kib)
    _DUMMY_HASH = _hasher.hash("not-a-real-password-0")


def hash_password(password: str) -> str:
    return _hasher.hash(password)


def verify_password(password_hash: str | None, password: str) -> bool:
    try:
        return _hasher.verify(password_hash or _DUMMY_HASH, password) and password_hash is not None
    except (VerifyMismatchError, VerificationError, InvalidHashError):
        return False


def new_token() -> str:
    return secrets.token_urlsafe(32)


def token_digest(secret_key: str, token: str) -> str:
    """Keyed hash of a token: the database never holds a usable token."""
    return hmac.new(secret_key.encode(), token.encode(), hashlib.sha256).hexdigest()


def lock_duration(failures: int, free: int, max_seconds: int) -> timedelta | None:
    """Lock-out after the ``free``-th failure: 1 s, 2 s, 4 s, ... capped at ``max_seconds``."""
    if failures < free:
        return None
    return timedelta(seconds=min(max_seconds, 2 ** (failures - free)))
