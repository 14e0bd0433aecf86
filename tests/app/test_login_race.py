"""Issue 36 finding 3: parallel wrong passwords cannot outrun the login lock.

Each attempt is counted atomically before its password is verified, so of N parallel wrong
passwords for one account at most ``login_free_failures`` reach the verification; the rest
answer 429. Verification is made slow here (0.3 s, what production argon2 costs) -- the window
in which the old code let every parallel attempt pass the check before the first failure was
recorded -- and the lock after the free failures long (60 s), so that no lock expires during
the test. Each request runs in its own thread with its own database connection, on SQLite and
PostgreSQL.
"""

from __future__ import annotations

import threading
import time
from datetime import timedelta

from fastapi.testclient import TestClient

from app import credentials
from tests.app.conftest import PASSWORD


def test_parallel_wrong_passwords_check_at_most_the_free_failures(env, monkeypatch):
    checked = {"n": 0}
    lock = threading.Lock()
    real_verify = credentials.verify_password

    def slow_verify(hash_, password):  # noqa: ANN001, ANN202
        with lock:
            checked["n"] += 1
        time.sleep(0.3)
        return real_verify(hash_, password)

    monkeypatch.setattr(credentials, "verify_password", slow_verify)
    monkeypatch.setattr(credentials, "lock_duration",
                        lambda f, free, cap: timedelta(seconds=60) if f >= free else None)
    n = 16
    codes: list[int] = []
    start = threading.Barrier(n)

    def attempt() -> None:
        with TestClient(env.app) as c:
            start.wait()
            r = c.post("/api/auth/login", json={"username": "annotator", "password": "wrong-pw!"})
            with lock:
                codes.append(r.status_code)

    threads = [threading.Thread(target=attempt) for _ in range(n)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(120)
    free = env.settings.login_free_failures
    assert len(codes) == n and set(codes) <= {401, 429}, codes
    assert checked["n"] <= free, f"{checked['n']} of {n} parallel wrong passwords were checked"
    assert codes.count(401) == checked["n"] and codes.count(429) == n - checked["n"]
    # the right password is refused too while the lock holds; an admin's unlock lifts it
    monkeypatch.setattr(credentials, "verify_password", real_verify)
    r = env.client.post("/api/auth/login", json={"username": "annotator", "password": PASSWORD})
    assert r.status_code == 429 and int(r.headers["Retry-After"]) > 1


def test_a_success_is_not_counted_against_the_address(env):
    free = env.settings.login_free_failures
    for _ in range(4 * free + 2):  # more logins from one address than its failure threshold
        r = env.client.post("/api/auth/login", json={"username": "annotator",
                                                     "password": PASSWORD})
        assert r.status_code == 200, r.text
