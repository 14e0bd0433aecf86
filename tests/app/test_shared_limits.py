"""Security round three (issue 36): limits counted in the database, one API process, SQLite and
PostgreSQL. (Two real API processes: tests/app/test_cross_process_limits.py.)

- viewer-socket leases: a process that stops renewing (killed) frees its places when the
  leases run out; one that runs keeps them;
- quotas on review items and comments: concurrent requests (threads, no process lock exists)
  pass at most the quota, each refusal a 429 naming the quota's variable.
"""

from __future__ import annotations

import dataclasses
import time
from concurrent.futures import ThreadPoolExecutor

import pytest

from app.shared_limits import SocketCapReached, SocketLeases, ViewerSocket


def test_viewer_socket_leases_of_a_stopped_process_expire(env):
    from sqlalchemy import func, select

    sessions = env.app.state.ctx.sessions
    a, b = SocketLeases(sessions, lease_s=1.0), SocketLeases(sessions, lease_s=1.0)
    a.claim("reviewer", 2)
    a.claim("reviewer", 2)
    with pytest.raises(SocketCapReached):
        b.claim("reviewer", 2)
    other = b.claim("admin", 2)  # another user is not affected
    time.sleep(1.5)  # longer than the lease: a renews its rows, they still count
    with pytest.raises(SocketCapReached):
        b.claim("reviewer", 2)
    a._stop.set()  # a is "killed": no renewal, no clean-up
    time.sleep(1.3)
    mine = b.claim("reviewer", 2)  # a's rows ran out: removed, a place is free
    with sessions() as s:
        users = sorted(s.scalars(select(ViewerSocket.username)))
    assert users == ["admin", "reviewer"], users
    b.release(other)
    b.release(mine)
    with sessions() as s:
        assert s.scalar(select(func.count()).select_from(ViewerSocket)) == 0
    b.close()
