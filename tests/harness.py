"""What every test directory shares: the data beside the clone, the synthetic scene made once per
run, free ports and the one live-server harness (in a thread or as a child process).

- :func:`shared_data` -- a path under ``../shared/data``; a test *fails* (never skips) when it
  is absent: CI always has it, so an absence is a broken checkout, not an optional extra.
- :func:`synth_scene` -- ``occufly.synthetic.generate(preset, seed)`` made once per test run
  (both halves of ``scripts/test.sh`` share it through ``OCCUFLY_TEST_CACHE``) and handed out
  read-only; :func:`synth_copy` gives a test its own copy inside a folder of its own.
- :class:`ThreadServer` -- uvicorn serving an app object in a thread, on a socket bound here
  (port 0), so no other process can be answering on that port.
- :class:`ProcessServer` -- uvicorn (or ``occufly serve``) as a child process on a free port; it
  counts as up only once ``/api/health`` answers 200 *and* the listening socket belongs to the
  child (or its children): a server that someone else runs on that port is never mistaken for it.
"""

from __future__ import annotations

import fcntl
import json
import shutil
import signal
import socket
import subprocess
import threading
import time
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO.parent / "shared" / "data"


# ---- the shared data ---------------------------------------------------------------------------
def shared_data(*parts: str) -> Path:
    """``../shared/data/<parts>``; fails the calling test, naming the path, when it is absent."""
    p = SHARED_DATA.joinpath(*parts)
    if not p.exists():
        pytest.fail(f"{p} is missing: the tests read the real photogrammetry exports of "
                    f"../shared/data beside the clone (CI always has them); restore that folder "
                    f"rather than skipping these tests", pytrace=False)
    return p


# ---- the synthetic scene, generated once per run ----------------------------------------------
def _listing(root: Path) -> dict[str, tuple[int, int]]:
    return {str(p.relative_to(root)): (p.stat().st_size, p.stat().st_mtime_ns)
            for p in sorted(root.rglob("*")) if p.is_file()}


class SynthCache:
    """``generate(preset, seed)`` outputs under ``root`` (one per key, made under a file lock so
    two pytest processes sharing ``root`` generate each scene once), with a listing of each to
    check at the end of the session that no test wrote into it."""

    def __init__(self, root: Path) -> None:
        self.root = Path(root)
        self.root.mkdir(parents=True, exist_ok=True)
        self.handed_out: dict[Path, dict] = {}

    def get(self, preset: str, seed: int) -> tuple[Path, dict]:
        from occufly.synthetic import generate

        key = f"{preset}-seed{seed}"
        out, summary = self.root / key / "scene", self.root / key / "summary.json"
        with open(self.root / f"{key}.lock", "w") as lock:
            fcntl.flock(lock, fcntl.LOCK_EX)  # the other half of the run may be generating it
            if not summary.is_file():
                # generate() builds under a temporary sibling and renames: no half scene here
                s = generate(out, preset=preset, seed=seed, overwrite=True)
                summary.write_text(json.dumps(s))
        if out not in self.handed_out:
            self.handed_out[out] = _listing(out)
        return out, json.loads(summary.read_text())

    def check_untouched(self) -> list[str]:
        """The scenes whose files changed since they were handed out (a test wrote into the
        shared copy instead of its own :func:`synth_copy`)."""
        return [str(p) for p, before in self.handed_out.items() if _listing(p) != before]


def synth_copy(src: Path, dest: Path) -> Path:
    """A test's own copy of a cached scene: real copies (a few MB), not hard links -- an import
    refuses hard-linked files in its root (issue 36: a link to a file outside the root), and a
    link would also make the cache's own files look linked. The session checks the cache is
    unchanged at its end."""
    shutil.copytree(src, dest, copy_function=shutil.copy2)
    return dest


# ---- ports and servers -------------------------------------------------------------------------
def free_port() -> int:
    """A port free at this moment (for a child process that binds it itself; a server in this
    process takes a bound socket instead, see :class:`ThreadServer`)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class ThreadServer:
    """``uvicorn`` serving ``app`` in a daemon thread on a socket bound here to a free loopback
    port (lifespan on, log level warning; ``config`` goes to ``uvicorn.Config``)."""

    def __init__(self, app, **config) -> None:  # noqa: ANN001
        import uvicorn

        self.app = app
        self.sock = socket.socket()
        self.sock.bind(("127.0.0.1", 0))
        self.port = self.sock.getsockname()[1]
        self.server = uvicorn.Server(uvicorn.Config(app, **{"log_level": "warning",
                                                             "lifespan": "on", **config}))
        self.thread = threading.Thread(target=self.server.run, kwargs={"sockets": [self.sock]},
                                       daemon=True)

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    def __enter__(self) -> ThreadServer:
        self.thread.start()
        t_end = time.monotonic() + 30
        while not self.server.started:
            if time.monotonic() > t_end or not self.thread.is_alive():
                self.sock.close()
                raise AssertionError("uvicorn did not start (see the log above)")
            time.sleep(0.02)
        return self

    def __exit__(self, *exc) -> None:  # noqa: ANN002
        self.server.should_exit = True
        self.thread.join(timeout=15)
        self.sock.close()


def _listens_on(pid: int, port: int) -> bool:
    import psutil

    try:
        proc = psutil.Process(pid)
        procs = [proc, *proc.children(recursive=True)]
    except psutil.NoSuchProcess:
        return False
    for p in procs:
        try:
            if any(c.status == psutil.CONN_LISTEN and c.laddr and c.laddr.port == port
                   for c in p.net_connections(kind="tcp")):
                return True
        except (psutil.NoSuchProcess, psutil.AccessDenied):
            continue
    return False


class ProcessServer:
    """A server as a child process on a free loopback port.

    ``argv`` is the command with ``{port}`` where the port goes (``{python}``: this
    interpreter; other braces must be doubled) (default: uvicorn serving
    ``app.main:app_from_env``); ``env`` its environment; its output goes to ``log`` (a path;
    shown when it fails to start). :meth:`start` waits until ``GET /api/health`` is 200 from
    *this* child; :meth:`kill9` and :meth:`start` again restart it on the same port."""

    UVICORN = ("{python}", "-m", "uvicorn", "app.main:app_from_env", "--factory", "--host",
               "127.0.0.1", "--port", "{port}", "--log-level", "warning")

    def __init__(self, env: dict, log: Path, argv=UVICORN, *, port: int | None = None,  # noqa: ANN001
                 start_timeout: float = 90.0) -> None:
        import sys

        self.env = env
        self.log = Path(log)
        self.port = port or free_port()
        self.argv = [a.format(port=self.port, python=sys.executable) for a in argv]
        self.start_timeout = start_timeout
        self.proc: subprocess.Popen | None = None

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    @property
    def pid(self) -> int:
        return self.proc.pid

    def log_tail(self, n: int = 3000) -> str:
        return self.log.read_text(errors="replace")[-n:] if self.log.is_file() else ""

    def start(self) -> ProcessServer:
        """:meth:`spawn` and :meth:`wait_ready`."""
        return self.spawn().wait_ready()

    def spawn(self) -> ProcessServer:
        """Start the child, without waiting (several servers may then start side by side)."""
        self.log.parent.mkdir(parents=True, exist_ok=True)
        with open(self.log, "ab") as log:
            self.proc = subprocess.Popen(self.argv, cwd=REPO, env=self.env, stdout=log,
                                         stderr=subprocess.STDOUT)
        return self

    def wait_ready(self) -> ProcessServer:
        """Until ``/api/health`` answers 200 from this child (an error naming the cause and
        the log's tail if it exits, times out, or someone else answers on the port)."""
        import httpx

        t_end = time.monotonic() + self.start_timeout
        while time.monotonic() < t_end:
            if self.proc.poll() is not None:
                raise AssertionError(f"{' '.join(self.argv)} exited ({self.proc.returncode}):\n"
                                     f"{self.log_tail()}")
            try:
                ok = httpx.get(f"{self.url}/api/health", timeout=2).status_code == 200
            except httpx.HTTPError:
                ok = False
            if ok:
                if not _listens_on(self.proc.pid, self.port):
                    self.stop()
                    raise AssertionError(f"port {self.port} answers /api/health, but not from "
                                         f"the server started here (pid {self.proc.pid}): "
                                         "another process took the port")
                return self
            time.sleep(0.1)
        self.stop()
        raise AssertionError(f"{' '.join(self.argv)} did not answer /api/health in "
                             f"{self.start_timeout:g} s:\n{self.log_tail()}")

    def kill9(self) -> None:
        self.proc.send_signal(signal.SIGKILL)
        self.proc.wait(10)

    def stop(self) -> None:
        if self.proc is None or self.proc.poll() is not None:
            return
        self.proc.send_signal(signal.SIGTERM)
        try:
            self.proc.wait(20)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait(5)

    def __enter__(self) -> ProcessServer:
        return self.start()

    def __exit__(self, *exc) -> None:  # noqa: ANN002
        self.stop()
