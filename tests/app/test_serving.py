"""Issue 24, finding 9: header-read and idle timeouts, the request-head size cap and
``--proxy-headers``, against a real ``occufly serve`` process on a loopback port.

Before the fix 50 connections that dribble a request head one header line at a time stayed
open for 60 s (uvicorn has no header-read timeout; its keep-alive timer starts only after a
response).
"""

from __future__ import annotations

import os
import selectors
import socket
import subprocess
import time
from pathlib import Path

import httpx
import pytest

from tests.harness import ProcessServer, free_port

REPO = Path(__file__).resolve().parents[2]
HEADER_TIMEOUT_S = 2.0
N_SLOW = 50


class ServeProcess(ProcessServer):
    """``occufly serve`` on a free port (tests.harness.ProcessServer: up once /api/health
    answers from this child), its output in ``tmp/serve.log``."""

    def __init__(self, tmp: Path, *extra: str, env: dict | None = None) -> None:
        env = {**os.environ, "OCCUFLY_DATA_DIR": str(tmp / "data"),
               "OCCUFLY_ENV": "development", "OCCUFLY_LIFTING": "off",
               "OCCUFLY_JOB_PROCESSES": "0", "OCCUFLY_ARGON2_MEMORY_KIB": "1024",
               "OCCUFLY_ARGON2_TIME_COST": "1",
               "OCCUFLY_HEADER_TIMEOUT_S": str(HEADER_TIMEOUT_S),
               "OCCUFLY_BODY_IDLE_TIMEOUT_S": str(HEADER_TIMEOUT_S), **(env or {})}
        super().__init__(env, tmp / "serve.log",
                         [str(REPO / ".venv" / "bin" / "occufly"), "serve", "--port", "{port}",
                          *extra])


def _closed_after(sockets: list[socket.socket], *, dribble: bool, limit_s: float) -> list:
    """Seconds until the server closed each socket (None: still open at limit_s). With
    ``dribble`` every open socket sends one more header line every 0.5 s."""
    sel = selectors.DefaultSelector()
    t0 = time.perf_counter()
    closed: dict[int, float] = {}
    for i, s in enumerate(sockets):
        s.setblocking(False)
        sel.register(s, selectors.EVENT_READ, i)
    next_drip = t0 + 0.5
    while len(closed) < len(sockets) and time.perf_counter() - t0 < limit_s:
        for key, _ev in sel.select(timeout=0.1):
            i = key.data
            try:
                data = key.fileobj.recv(4096)
            except (ConnectionResetError, BlockingIOError) as e:
                data = b"" if isinstance(e, ConnectionResetError) else None
            if data == b"":
                closed[i] = time.perf_counter() - t0
                sel.unregister(key.fileobj)
        if dribble and time.perf_counter() >= next_drip:
            next_drip += 0.5
            for i, s in enumerate(sockets):
                if i not in closed:
                    try:
                        s.send(b"X-Slow: 1\r\n")
                    except OSError:
                        closed[i] = time.perf_counter() - t0
                        sel.unregister(s)
    sel.close()
    return [closed.get(i) for i in range(len(sockets))]


@pytest.fixture(scope="module")
def served(tmp_path_factory):
    with ServeProcess(tmp_path_factory.mktemp("serve")) as srv:
        yield srv


def test_slow_and_silent_request_heads_are_closed(served):
    """50 slow-header ("slowloris") connections and 50 silent ones are closed ~2 s
    (OCCUFLY_HEADER_TIMEOUT_S) after they opened, while requests keep being answered."""
    slow = [socket.create_connection(("127.0.0.1", served.port)) for _ in range(N_SLOW)]
    for s in slow:
        s.sendall(b"GET /api/health HTTP/1.1\r\nHost: 127.0.0.1\r\n")
    silent = [socket.create_connection(("127.0.0.1", served.port)) for _ in range(N_SLOW)]
    t = _closed_after(slow + silent, dribble=True, limit_s=20.0)
    # meanwhile the server still answers (measured after: they were open in parallel)
    assert httpx.get(f"{served.url}/api/health", timeout=5).status_code == 200
    for s in slow + silent:
        s.close()
    still_open = [i for i, x in enumerate(t) if x is None]
    assert not still_open, f"{len(still_open)} connections still open after 20 s"
    worst = max(t)
    assert HEADER_TIMEOUT_S - 0.5 <= min(t) and worst <= HEADER_TIMEOUT_S + 3.0, t
    print(f"\n{2 * N_SLOW} slow/silent connections closed after {min(t):.2f}-{worst:.2f} s "
          f"(header timeout {HEADER_TIMEOUT_S} s)")


def test_keep_alive_idle_and_second_slow_head_are_closed(served):
    """After a response the connection may idle for the keep-alive time (5 s) only, and a
    second request head on it has the same header-read deadline."""
    s = socket.create_connection(("127.0.0.1", served.port))
    s.sendall(b"GET /api/health HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n")
    s.settimeout(10)
    assert b"200 OK" in s.recv(65536)
    s.sendall(b"GET /api/health HTTP/1.1\r\n")  # a second head that never completes
    t = _closed_after([s], dribble=True, limit_s=15.0)
    s.close()
    assert t[0] is not None and t[0] <= HEADER_TIMEOUT_S + 3.0, t
    idle = socket.create_connection(("127.0.0.1", served.port))
    idle.sendall(b"GET /api/health HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n")
    idle.settimeout(10)
    assert b"200 OK" in idle.recv(65536)
    t = _closed_after([idle], dribble=False, limit_s=15.0)
    idle.close()
    assert t[0] is not None and t[0] <= 5 + 2.0, t


def test_stalled_request_bodies_are_closed(served):
    """50 connections that send a complete head announcing a body, part of it, then nothing:
    closed ~2 s (OCCUFLY_BODY_IDLE_TIMEOUT_S) after the last byte."""
    socks = [socket.create_connection(("127.0.0.1", served.port)) for _ in range(N_SLOW)]
    for s in socks:
        s.sendall(b"POST /api/auth/login HTTP/1.1\r\nHost: 127.0.0.1\r\n"
                  b"Content-Type: application/json\r\nContent-Length: 1000\r\n\r\n{\"user")
    t = _closed_after(socks, dribble=False, limit_s=20.0)
    for s in socks:
        s.close()
    assert all(x is not None for x in t), f"{sum(x is None for x in t)} still open after 20 s"
    assert HEADER_TIMEOUT_S - 0.5 <= min(t) and max(t) <= HEADER_TIMEOUT_S + 3.0, t
    print(f"\n{N_SLOW} stalled bodies closed after {min(t):.2f}-{max(t):.2f} s")


def test_oversized_request_head_is_refused_at_once(served):
    s = socket.create_connection(("127.0.0.1", served.port))
    s.settimeout(10)
    s.sendall(b"GET /api/health HTTP/1.1\r\nHost: 127.0.0.1\r\nX-Big: " + b"a" * (200 << 10))
    got = b""
    try:
        while True:
            chunk = s.recv(65536)
            if not chunk:
                break
            got += chunk
    except (ConnectionResetError, TimeoutError):
        pass
    s.close()
    assert got.startswith(b"HTTP/1.1 400"), got[:200]


def test_proxy_headers_only_from_trusted_proxies(tmp_path):
    """``--proxy-headers`` believes X-Forwarded-Proto from OCCUFLY_TRUSTED_PROXIES: the session
    cookie is Secure behind a TLS proxy; without --proxy-headers the header is ignored; with it
    but no trusted proxy configured, serve refuses to start."""
    from app.config import Settings
    from app.users import service as users

    def seed(data: Path) -> None:
        from app.main import close, create_app

        app = create_app(Settings(data_dir=data, env="development", job_processes=False,
                                  live_lifting=False, argon2_memory_kib=1024,
                                  argon2_time_cost=1))
        with app.state.ctx.sessions() as s:
            users.create_user(session=s, username="rev", password="correct-horse-battery",
                              role="reviewer")
        close(app)

    seed(tmp_path / "data")
    body = {"username": "rev", "password": "correct-horse-battery"}
    fwd = {"X-Forwarded-Proto": "https", "X-Forwarded-For": "203.0.113.7"}
    with ServeProcess(tmp_path, "--proxy-headers",
                      env={"OCCUFLY_TRUSTED_PROXIES": "127.0.0.1"}) as srv:
        r = httpx.post(f"{srv.url}/api/auth/login", json=body, headers=fwd)
        assert r.status_code == 200, r.text
        assert "secure" in r.headers["set-cookie"].lower(), r.headers["set-cookie"]
    with ServeProcess(tmp_path) as srv:
        r = httpx.post(f"{srv.url}/api/auth/login", json=body, headers=fwd)
        assert r.status_code == 200 and "secure" not in r.headers["set-cookie"].lower()
    p = subprocess.run([str(REPO / ".venv/bin/occufly"), "serve", "--proxy-headers", "--port",
                        str(free_port())], env={**os.environ, "OCCUFLY_ENV": "development",
                                                 "OCCUFLY_DATA_DIR": str(tmp_path / "data"),
                                                 "OCCUFLY_TRUSTED_PROXIES": ""},
                       capture_output=True, text=True, timeout=60)
    assert p.returncode != 0 and "OCCUFLY_TRUSTED_PROXIES" in p.stderr + p.stdout, p


def test_nginx_tls_example_gives_secure_cookies(tmp_path):
    """deploy/nginx.conf as shipped (upstream and ports moved to loopback, a self-signed
    certificate) in front of ``occufly serve --proxy-headers``: http redirects to https, the
    login over TLS sets a Secure session cookie, the app sees the client's address."""
    import re
    import shutil

    nginx = shutil.which("nginx") or "/usr/sbin/nginx"
    assert Path(nginx).is_file(), "nginx is needed (scripts/setup.sh --test installs it)"
    subprocess.run(["openssl", "req", "-x509", "-newkey", "rsa:2048", "-nodes", "-days", "1",
                    "-subj", "/CN=127.0.0.1", "-keyout", str(tmp_path / "privkey.pem"),
                    "-out", str(tmp_path / "fullchain.pem")], check=True, capture_output=True)
    seed_dir = tmp_path / "srv"
    p80, p443 = free_port(), free_port()
    with ServeProcess(seed_dir, "--proxy-headers",
                      env={"OCCUFLY_TRUSTED_PROXIES": "127.0.0.1"}) as srv:
        conf = (REPO / "deploy" / "nginx.conf").read_text()
        subs = [(r"server api:8000;", f"server 127.0.0.1:{srv.port};"),
                (r"listen 80;", f"listen 127.0.0.1:{p80};"),
                (r"listen 443 ssl;", f"listen 127.0.0.1:{p443} ssl;"),
                (r"/etc/nginx/tls/", f"{tmp_path}/"),
                (r"return 301 https://\$host\$request_uri;",
                 f"return 301 https://$host:{p443}$request_uri;")]
        for pat, rep in subs:
            conf, n = re.subn(pat, rep, conf)
            assert n >= 1, f"deploy/nginx.conf no longer has {pat!r}"
        version = subprocess.run([nginx, "-v"], capture_output=True, text=True).stderr
        m = re.search(r"nginx/(\d+)\.(\d+)", version)
        if m and (int(m.group(1)), int(m.group(2))) < (1, 25):
            conf = conf.replace("    http2 on;\n", "")  # the compose image is nginx 1.27
        (tmp_path / "site.conf").write_text(conf)
        (tmp_path / "main.conf").write_text(
            f"pid {tmp_path}/nginx.pid;\nerror_log {tmp_path}/error.log;\nevents {{}}\n"
            f"http {{\n access_log off;\n client_body_temp_path {tmp_path}/cb;\n"
            f" proxy_temp_path {tmp_path}/px;\n include {tmp_path}/site.conf;\n}}\n")
        proc = subprocess.Popen([nginx, "-p", str(tmp_path), "-c", str(tmp_path / "main.conf"),
                                 "-g", "daemon off;"], stdout=subprocess.PIPE,
                                stderr=subprocess.STDOUT)
        try:
            base = f"https://127.0.0.1:{p443}"
            t_end = time.monotonic() + 20
            while True:
                try:
                    if httpx.get(f"{base}/api/health", verify=False, timeout=2).status_code == 200:
                        break
                except httpx.HTTPError:
                    pass
                assert proc.poll() is None, proc.stdout.read().decode()
                assert time.monotonic() < t_end, "nginx did not answer"
                time.sleep(0.2)
            r = httpx.get(f"http://127.0.0.1:{p80}/api/health")
            assert r.status_code == 301 and r.headers["location"].startswith("https://")
            r = httpx.post(f"{base}/api/auth/login", verify=False,
                           json={"username": "nobody", "password": "x" * 12})
            assert r.status_code == 401  # the app answered through TLS (no such user)
            r = httpx.get(f"{base}/", verify=False)
            assert r.status_code == 200 and "script-src 'self'" in r.headers[
                "content-security-policy"]
            assert r.headers.get("strict-transport-security")
            # a real login: the cookie is Secure because the app saw https from its proxy
            from app.config import Settings
            from app.main import close, create_app
            from app.users import service as users

            app = create_app(Settings(data_dir=seed_dir / "data", env="development",
                                      job_processes=False, live_lifting=False,
                                      argon2_memory_kib=1024, argon2_time_cost=1))
            with app.state.ctx.sessions() as s:
                users.create_user(session=s, username="rev", password="correct-horse-battery",
                                  role="reviewer")
            close(app)
            r = httpx.post(f"{base}/api/auth/login", verify=False,
                           json={"username": "rev", "password": "correct-horse-battery"})
            assert r.status_code == 200, r.text
            cookie = r.headers["set-cookie"].lower()
            assert "secure" in cookie and "httponly" in cookie, cookie
        finally:
            proc.terminate()
            proc.wait(10)


_KEEP_PROBE = r"""
import os, resource, sys
import numpy as np
from app.serving import tune_allocator
tuned = tune_allocator()
def request():  # a review's temporaries: a dozen 20 MB blocks, allocated, used, freed
    blocks = [np.ones(20 << 20, np.uint8) for _ in range(12)]
    del blocks
for _ in range(3):
    request()
r0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
request()
print(int(tuned), resource.getrusage(resource.RUSAGE_SELF).ru_minflt - r0)
"""


def test_a_serving_process_keeps_freed_heap_for_its_next_request(monkeypatch):
    """tune_allocator (every `occufly serve` process): the freed blocks of one request are
    reused by the next without page faults; with OCCUFLY_MALLOC_KEEP_MB=0 (glibc's defaults)
    the 240 MB go back to the system and are faulted in again; an operator's own malloc
    environment wins; a bad value is refused naming the variable."""
    import platform
    import sys

    from app.serving import malloc_keep_mb
    from occufly.errors import InputFormatError

    if platform.libc_ver()[0] != "glibc":
        pytest.skip("glibc's mallopt: the deployment's C library")
    base = {k: v for k, v in os.environ.items()
            if not k.startswith(("MALLOC_", "GLIBC_TUNABLES", "OCCUFLY_MALLOC"))}

    def probe(**extra: str) -> tuple[int, int]:
        out = subprocess.run([sys.executable, "-c", _KEEP_PROBE], env={**base, **extra}, cwd=REPO,
                             capture_output=True, text=True, timeout=120)
        assert out.returncode == 0, out.stderr
        tuned, faults = out.stdout.split()
        return int(tuned), int(faults)

    tuned, kept = probe()
    assert tuned == 1 and kept < 50, kept
    tuned, default = probe(OCCUFLY_MALLOC_KEEP_MB="0")
    # at least one fault per 2 MB huge page of the 240 MB, 4 kB pages many more
    assert tuned == 0 and default >= 100, default
    assert probe(MALLOC_TRIM_THRESHOLD_="131072")[0] == 0
    for bad in ("lots", "-1", "5000", "1.5"):
        monkeypatch.setenv("OCCUFLY_MALLOC_KEEP_MB", bad)
        with pytest.raises(InputFormatError, match="OCCUFLY_MALLOC_KEEP_MB"):
            malloc_keep_mb()
    monkeypatch.delenv("OCCUFLY_MALLOC_KEEP_MB")
    assert malloc_keep_mb() == 512
