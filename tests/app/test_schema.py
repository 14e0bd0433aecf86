"""Migrations vs models (no drift) on both databases, settings, OpenAPI validity, fuzzing."""

from __future__ import annotations

import pytest
from alembic.autogenerate import compare_metadata
from alembic.runtime.migration import MigrationContext

from app import db
from app.config import ConfigError, Settings
from app.models import metadata


@pytest.mark.parametrize("backend", ["sqlite", "postgresql"])
def test_migrations_match_models(backend, tmp_path, request):
    url = f"sqlite:///{tmp_path / 'm.db'}" if backend == "sqlite" else request.getfixturevalue("pg_url")
    db.upgrade(url)
    assert db.current_revision(url) == _head()
    engine = db.make_engine(url, pooled=False)
    with engine.connect() as conn:
        diff = compare_metadata(MigrationContext.configure(conn, opts={"compare_type": True}),
                                metadata)
    engine.dispose()
    assert diff == []


def _head() -> str:
    from alembic.script import ScriptDirectory

    head = ScriptDirectory.from_config(db.alembic_config("sqlite://")).get_current_head()
    assert head >= "0002"
    return head


def test_drift_check_detects_a_missing_column(tmp_path):
    """The no-drift assertion above would fail if models and migrations disagreed."""
    import sqlalchemy as sa

    url = f"sqlite:///{tmp_path / 'm.db'}"
    db.upgrade(url)
    engine = db.make_engine(url, pooled=False)
    with engine.begin() as conn:
        conn.execute(sa.text("ALTER TABLE jobs DROP COLUMN attempts"))
    with engine.connect() as conn:
        diff = compare_metadata(MigrationContext.configure(conn), metadata)
    engine.dispose()
    assert any(d[0] == "add_column" and d[3].name == "attempts" for d in diff)


def test_settings_from_env_and_secret_refusal(tmp_path):
    with pytest.raises(ConfigError, match="OCCUFLY_SECRET_KEY"):
        Settings.from_env({"OCCUFLY_DATA_DIR": str(tmp_path)})
    s = Settings.from_env({"OCCUFLY_DATA_DIR": str(tmp_path), "OCCUFLY_ENV": "development",
                           "OCCUFLY_MAX_UPLOAD_MB": "2", "OCCUFLY_IMPORT_ROOTS": "/a:/b"})
    assert s.database_url == f"sqlite:///{tmp_path / 'occufly.db'}"
    assert s.max_upload_bytes == 2 * 1024 * 1024 and [str(p) for p in s.import_roots] == ["/a", "/b"]
    s = Settings.from_env({"OCCUFLY_SECRET_KEY": "x" * 32, "OCCUFLY_DATABASE_URL": "sqlite:///q.db"})
    assert s.database_url == "sqlite:///q.db" and not s.is_dev
    with pytest.raises(ConfigError, match="OCCUFLY_MAX_UPLOAD_MB"):
        Settings.from_env({"OCCUFLY_ENV": "development", "OCCUFLY_MAX_UPLOAD_MB": "lots"})


def test_openapi_schema_is_valid_and_complete(env):
    from openapi_spec_validator import validate

    spec = env.client.get("/openapi.json").json()
    validate(spec)
    paths = spec["paths"]
    for p in ["/api/auth/login", "/api/scenes/{sid}/next", "/api/frames/{fid}/mask",
              "/api/frames/{fid}/mask/versions/{vid}/restore", "/api/jobs/{jid}/resume",
              "/api/scenes/{sid}/labels/status", "/api/review-items/{rid}"]:
        assert p in paths, p
    assert "image/png" in paths["/api/frames/{fid}/mask"]["put"]["requestBody"]["content"]


def test_schemathesis_finds_no_server_errors(world_for_fuzz):
    """Property-based run over EVERY operation, destructive ones included (logout, password
    changes, session revocation, imports, jobs), as an admin and as an annotator, on a
    disposable data dir: never a 5xx. Each case gets a fresh token, so a case that ends its
    session cannot starve the rest. Bounded: 5 examples per operation and identity."""
    import os

    import schemathesis
    from hypothesis import HealthCheck, given, settings
    from schemathesis.checks import not_a_server_error

    from app.users import service as users

    env, _headers = world_for_fuzz
    schema = schemathesis.openapi.from_asgi("/openapi.json", env.app)

    def fresh(name: str) -> dict:
        with env.app.state.ctx.sessions() as s:
            token = users.issue_token(session=s, settings=env.settings,
                                      user=users.get_by_name(session=s, username=name))
        return {"Authorization": f"Bearer {token}"}

    failures: list[str] = []
    codes: list[int] = []
    n_ops = 0
    for result in schema.get_all_operations():
        op = result.ok()
        n_ops += 1
        for who in ("admin", "annotator"):
            def make(who: str, op=op):  # noqa: ANN001, ANN202 - one test per operation and identity
                @settings(max_examples=5, deadline=None, database=None,
                          suppress_health_check=list(HealthCheck))
                @given(case=op.as_strategy())
                def run(case):
                    resp = case.call(headers=fresh(who))
                    codes.append(resp.status_code)
                    try:
                        case.validate_response(resp, checks=(not_a_server_error,))
                    except Exception as e:  # noqa: BLE001 - collect all failing operations
                        failures.append(f"{who} {case.method} {case.formatted_path}: "
                                        f"{str(e)[:300]}")

                return run

            make(who)()
    assert n_ops >= 50
    assert failures == []
    # the run really exercised the API: many calls, some of them successful
    assert len(codes) >= 2 * n_ops and sum(200 <= c < 300 for c in codes) >= 20, sorted(set(codes))
    out = os.environ.get("OCCUFLY_FUZZ_COUNTS")
    if out:
        import json

        with open(out, "a") as f:
            f.write(json.dumps({"backend": env.backend, "operations": n_ops, "cases": len(codes),
                                "server_errors": len(failures)}) + "\n")


@pytest.fixture
def world_for_fuzz(env):
    headers = env.bearer("admin")
    scene = env.import_tiny(headers)
    env.select_all(scene["id"])
    return env, headers
