"""Session fixtures of the whole suite (helpers in tests/harness.py).

- ``synth_tiny``: the synthetic ``tiny`` scene (seed 0), generated once per run and shared
  read-only; both pytest processes of ``scripts/test.sh`` share it through ``OCCUFLY_TEST_CACHE``.
- the ``slow`` marker on the modules listed in ``SLOW`` (with why): ``scripts/test.sh`` runs
  them in the browser lane, which otherwise waits on Chromium; ``-m "not slow"`` is a quick loop.
- a fixed memory budget: ``occufly.fsutil.available_memory`` answers ``TEST_MEMORY_BYTES`` in
  this process, so a step's up-front memory check (``require_memory``) gives the same answer on
  every run instead of depending on what the other processes of a shared machine hold at that
  moment; a test whose step would need more than that fails, every time. Tests that check the
  refusal monkeypatch it lower themselves.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from tests.harness import SynthCache

TEST_MEMORY_BYTES = 8 << 30  # the suite's steps need < 1 GB each; CI machines have >= 8 GB

# tests outside tests/e2e and tests/viewer that run for tens of seconds each: path (relative to
# the repository, a module or module::test prefix) -> why. Chosen from --durations of both
# lanes (issue 38, a loaded 2-core machine): the non-browser lane took 3,507 s, the browser
# lane 673 s; these are ~1,300 s of the former. scripts/test.sh prints each lane's
# --durations=15 so the list can follow the suite. test_schema.py (schemathesis against every
# route) and the access-table test (~45 s together) went back to the other lane on 6 December:
# it lost ~2 min of waits (a PostgreSQL app's close() waited out the LISTEN heartbeat, 0.5 s;
# TRUNCATE per test, 0.2 s), so the browser lane became the longer.
SLOW = {
    "tests/app/test_job_faults.py": "kill -9 of a server process mid-export, restart, resume",
    "tests/app/test_topology.py": "two API processes, a lifting worker and Dask, kill -9 twice",
    "tests/app/test_serving.py": "`occufly serve` and nginx processes, header/idle timeouts",
    "tests/app/test_cross_process_limits.py":
        "two API processes on PostgreSQL: job quota, viewer-socket cap and access across them",
    "tests/app/test_shared_limits.py::test_serialise_holds_between_two_processes":
        "two child processes racing for a quota's last places, SQLite and PostgreSQL",
    "tests/test_scale.py": "the 960 x 640 `tinyfull` scene, renders of full-size frames",
    "tests/test_synthetic_formats.py": "the tiny scene written in every photogrammetry format",
    "tests/app/test_corrections_api.py::test_kill9_during_an_edit_leaves_it_entirely_applied_or_not_at_all":
        "kill -9 of a child process in the middle of an edit",
    "tests/test_fsutil.py::test_sigterm_unwinds_a_command_and_leaves_no_partial_output":
        "`occufly synth` / `occufly import` child processes stopped by SIGTERM",
    # the app served in a child process (its own peak memory, raw sockets); moved here from
    # the other lane to even the two (issue 38: 13 min 29 s against 10 min 22 s, 6 December;
    # these modules ~86 s together, measured on their own on a quiet machine)
    # (test_attack_probes.py and test_header_probes.py, ~25 s together, went back to the other
    # lane in stop 49, once the shared resolved routes took it from 12:06 to 9:17 and this one
    # stayed at 10:22)
    "tests/app/test_import_memory.py": "imports of bombs and huge files, the server's peak memory",
    "tests/app/test_correction_parsing.py": "1 M - 10 M point corrections streamed to a served app",
    "tests/app/test_body_rate.py": "slow uploads over raw sockets, timed",
    "tests/app/test_body_limits.py": "a 200 MB body against a served app, its peak memory",
    # moved to even the lanes again (stop 48: the other lane 12:20, this one 10:49)
    "tests/app/test_review_refresh_process.py":
        "the after-fill review refresh in child processes, niced, killed, orphaned",
}


# scripts/test.sh runs tests/e2e and tests/viewer whole in the browser lane, then SLOW: a path
# in both would run twice
assert not [k for k in SLOW if k.startswith(("tests/e2e", "tests/viewer"))], SLOW


def pytest_itemcollected(item) -> None:  # noqa: ANN001
    rel = item.nodeid
    if any(rel == k or rel.startswith(k + "::") or rel.startswith(k + "[") for k in SLOW):
        item.add_marker(pytest.mark.slow)


@pytest.fixture(scope="session", autouse=True)
def fixed_memory_budget():
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr("occufly.fsutil.available_memory", lambda: TEST_MEMORY_BYTES)
        yield TEST_MEMORY_BYTES


@pytest.fixture(scope="session")
def synth_cache(tmp_path_factory) -> SynthCache:
    root = os.environ.get("OCCUFLY_TEST_CACHE")
    cache = SynthCache(Path(root) if root else tmp_path_factory.mktemp("synth-cache"))
    yield cache
    changed = cache.check_untouched()
    assert not changed, (f"a test wrote into the shared synthetic scene(s) {changed}: take a "
                         "copy (tests.harness.synth_copy) before changing it")


@pytest.fixture(scope="session")
def synth_tiny(synth_cache) -> Path:
    """The ``tiny`` synthetic scene, seed 0 (read-only: copy it with synth_copy to change it)."""
    return synth_cache.get("tiny", 0)[0]
