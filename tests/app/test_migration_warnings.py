"""Issue 40 defect 8: the first ``occufly demo`` on a fresh machine printed an SQLAlchemy
``SAWarning`` ("Skipped unsupported reflection of expression-based index
uq_users_username_lower") before its progress lines. Cause: on SQLite, Alembic's batch mode
rebuilds a table by reflecting it, and reflection followed its foreign keys to ``users``,
whose functional index ``lower(username)`` SQLite reflection cannot represent. The batch
operations reflect their own table only (``reflect_kwargs={'resolve_fks': False}``)."""

from __future__ import annotations

import os
import subprocess
import sys
import warnings

from sqlalchemy.exc import SAWarning

from app import db


def test_a_fresh_migrate_prints_no_sawarning(tmp_path):
    """What the demo's first start runs, in a new process (no warning registry), every
    warning shown."""
    env = {**os.environ, "OCCUFLY_DATA_DIR": str(tmp_path / "data"), "OCCUFLY_ENV": "development",
           "PYTHONWARNINGS": "always"}
    env.pop("OCCUFLY_DATABASE_URL", None)
    r = subprocess.run([sys.executable, "-c", "import sys; from occufly.cli import main; sys.exit(main())",
                        "db", "upgrade"], env=env,
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-3000:]
    assert (tmp_path / "data" / "occufly.db").is_file()
    assert "SAWarning" not in r.stderr, r.stderr[-3000:]


def test_migrations_up_down_up_raise_no_sawarning(tmp_path):
    from alembic import command

    url = f"sqlite:///{tmp_path / 'm.db'}"
    with warnings.catch_warnings():
        warnings.simplefilter("error", SAWarning)
        db.upgrade(url)
        command.downgrade(db.alembic_config(url), "base")
        db.upgrade(url)
