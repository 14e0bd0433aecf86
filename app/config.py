"""Application settings, read from ``OCCUFLY_*`` environment variables.

=============================  ===========================================================
``OCCUFLY_DATA_DIR``           data directory (default ``./data``): database file, mask
                               store, scene workspaces, exports
``OCCUFLY_DATABASE_URL``       SQLAlchemy URL (default ``sqlite:///<data_dir>/occufly.db``;
                               PostgreSQL: ``postgresql+psycopg://user:pw@host/db``)
``OCCUFLY_IMPORT_ROOTS``       ``os.pathsep``-separated folders admins may import from
                               (default ``<data_dir>/imports``)
``OCCUFLY_SECRET_KEY``         secret for token hashing; the built-in default is refused
                               unless ``OCCUFLY_ENV=development``
``OCCUFLY_ENV``                ``production`` (default) or ``development``
``OCCUFLY_DASK_ADDRESS``       Dask scheduler address; unset = local process pool
``OCCUFLY_MAX_UPLOAD_MB``      largest accepted mask upload (default 64)
``OCCUFLY_LEASE_MINUTES``      how long ``next`` holds a frame for an annotator (default 30)
``OCCUFLY_SESSION_HOURS``      login token lifetime (default 12)
``OCCUFLY_FILL_DEBOUNCE_S``    quiet time before kNN fill/denoise reruns (default 5)
``OCCUFLY_FILL_SETTLE_S``      quiet time after which a scene filled with the robust decision's
                               held model is decided again with a refitted one (default 120;
                               0 = only when the model is refitted anyway)
``OCCUFLY_FILL_NICE``          niceness added to the lifting worker's fill thread (default 5,
                               0 = none): saves and page requests go first on a busy host
``OCCUFLY_REVIEW_REFRESH_PROCESS``  1 (default): the review's after-fill refresh (stored
                               agreement of up to 200 frames, suspects) runs in a child process
                               of the lifting worker; 0: in its fill thread (tests, debugging)
``OCCUFLY_REVIEW_REFRESH_NICE``  niceness of that child process (default 10, 0..19)
``OCCUFLY_JOB_WORKERS``        concurrently running jobs (default 2)
``OCCUFLY_JOB_PROCESSES``      1 (default): heavy jobs run in worker processes (or on Dask);
                               0: in threads of the server process (debugging)
``OCCUFLY_LIFTING``            ``embedded`` (default: the lifting worker runs in the server
                               process), ``external`` (a separate ``occufly lifting-worker``;
                               what ``occufly serve --workers N`` starts) or ``off``
``OCCUFLY_AUTO_UPGRADE``       1 (default): Alembic upgrade at start-up; 0: never (``occufly
                               serve --workers N`` upgrades once, before the workers start)
``OCCUFLY_FRONTEND_DIR``       static frontend folder (default ``<repo>/frontend``)
``OCCUFLY_ARGON2_MEMORY_KIB``  argon2id memory cost (default 65536 = argon2-cffi's default)
``OCCUFLY_ARGON2_TIME_COST``   argon2id iterations (default 3)
``OCCUFLY_TRUSTED_PROXIES``    comma-separated addresses of reverse proxies whose
                               ``X-Forwarded-For`` is believed (default: none, the peer
                               address is the client)
``OCCUFLY_VIEWER_SOCKETS_PER_USER``  open 3D viewer sockets per user and API process
                               (default 4; each holds its own copy of the scene in viser)
``OCCUFLY_HEADER_TIMEOUT_S``   a connection's request head must be complete within this
                               (default 10 s; see app/serving.py)
``OCCUFLY_ALLOWED_ORIGINS``    comma-separated extra origins (``https://host:port``) allowed to
                               send cookie-authenticated writes besides the app's own host
``OCCUFLY_MAX_IMPORT_UPLOAD_MB``  largest zip of a project folder uploaded from the import
                               form (default 8192; extracted at most 4x that:
                               app/scenes/imports.py)
``OCCUFLY_EXPORT_KEEP_LAST``   export retention: keep only the newest N finished exports of
                               each scene (default 0 = keep all)
``OCCUFLY_EXPORT_MAX_AGE_DAYS``  export retention: delete finished exports older than this
                               (default 0 = never); both applied at start-up and after each
                               export (app/scenes/disk.py)
``OCCUFLY_MAX_JSON_MB``        largest JSON request body (default 1; 413 beyond, checked
                               before the body is read: app/bodylimit.py)
``OCCUFLY_MAX_SELECTION_MB``   largest point-id list body (corrections, review items;
                               default 64)
``OCCUFLY_MAX_CORRECTION_POINTS``  point ids one 3D correction may name (default 2000000;
                               413 beyond, counted before the ids are parsed)
``OCCUFLY_USER_QUOTA_MB``      mask storage one user's versions may take, conflicts included
                               (default 2048; 507 beyond)
``OCCUFLY_SCENE_QUOTA_MB``     mask storage one scene's versions may take (default 10240)
``OCCUFLY_ACTIVE_JOBS_PER_USER``  queued + running jobs one user may have (default 4; 429)
``OCCUFLY_EXPORT_QUOTA_MB``    disk the exports folder may take before new exports are
                               refused (default 51200; 507)
=============================  ===========================================================
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

from occufly.errors import OccuflyError

DEFAULT_SECRET = "occufly-insecure-development-secret"
REPO_ROOT = Path(__file__).resolve().parent.parent


class ConfigError(OccuflyError):
    """The environment does not describe a usable configuration."""


@dataclass
class Settings:
    data_dir: Path = Path("data")
    database_url: str = ""
    import_roots: list[Path] = field(default_factory=list)
    secret_key: str = DEFAULT_SECRET
    env: str = "production"
    dask_address: str | None = None
    max_upload_bytes: int = 64 * 1024 * 1024
    lease_seconds: int = 30 * 60
    reject_hold_seconds: int = 24 * 3600
    # review (issue 23): below this share of a frame's painted pixels with independent evidence
    # (other frames' votes or fill) its LOO agreement is not shown (docs/review.md)
    min_independent_coverage: float = 0.5
    session_seconds: int = 12 * 3600
    fill_debounce_s: float = 5.0
    # issue 37, eighth round: a fill after a save keeps the robust decision's fitted model
    # (occufly.lifting.robust.HeldDecision); once the scene has been quiet this long, it is
    # filled once more with the model fitted again, so the labels stop depending on the order
    # of the saves (0 = not on a timer)
    fill_settle_s: float = 120.0
    # issue 38: how long GET /scenes/{sid}/quality waits for a report being computed before
    # it answers with the last one (stale) or 202 (none yet); the computation goes on
    quality_wait_s: float = 1.5
    fill_nice: int = 5  # the fill thread's added niceness (0..19; docs/lifting-scale.md)
    # issue 38: the review's after-fill refresh in a niced child process (app.review.refresher)
    review_refresh_process: bool = True
    review_refresh_nice: int = 10
    job_workers: int = 2
    job_processes: bool = True
    frontend_dir: Path = REPO_ROOT / "frontend"
    docs_site_dir: Path = REPO_ROOT / "site"  # the built documentation (mkdocs build), at /help/
    login_free_failures: int = 5  # failures before a key gets locked out
    login_max_lock_s: int = 300
    argon2_memory_kib: int = 65536
    argon2_time_cost: int = 3
    auto_upgrade: bool = True
    live_lifting: bool = True
    lifting: str = "embedded"  # embedded | external | off (see app.lifting.client)
    trusted_proxies: list[str] = field(default_factory=list)
    allowed_origins: list[str] = field(default_factory=list)
    login_user_free_factor: int = 10  # an account's failures from all addresses before a lock
    login_user_max_lock_s: int = 60  # ... which is short: an attacker cannot keep it locked
    session_check_s: float = 2.0  # how often an open viewer socket re-checks its session
    # issue 28: the import form's zip upload, export retention (0 = off)
    max_import_upload_bytes: int = 8192 << 20
    export_keep_last: int = 0
    export_max_age_days: float = 0.0
    # issue 24: request body caps (app/bodylimit.py), storage and job quotas
    max_json_bytes: int = 1 << 20
    max_selection_bytes: int = 64 << 20
    max_correction_points: int = 2_000_000  # issue 36: a 1 M-point lasso fits (issue 38)
    user_quota_bytes: int = 2048 << 20
    scene_quota_bytes: int = 10240 << 20
    active_jobs_per_user: int = 4
    export_quota_bytes: int = 51200 << 20
    viewer_sockets_per_user: int = 4  # open 3D viewer sockets per user (all API processes)
    # issue 36: review items and comments, counted in the database (app.review.service)
    open_review_items_per_user: int = 500  # open items one user filed in one scene
    comments_per_user_hour: int = 300  # comments (a new item's first included) per user
    comments_per_item: int = 500  # comments in one item's thread

    def __post_init__(self) -> None:
        self.data_dir = Path(self.data_dir).absolute()
        if not self.database_url:
            self.database_url = f"sqlite:///{self.data_dir / 'occufly.db'}"
        if not self.import_roots:
            self.import_roots = [self.data_dir / "imports"]
        self.import_roots = [Path(p).absolute() for p in self.import_roots]
        self.frontend_dir = Path(self.frontend_dir)
        self.docs_site_dir = Path(self.docs_site_dir)
        if self.lifting not in ("embedded", "external", "off"):
            raise ConfigError(f"OCCUFLY_LIFTING must be 'embedded', 'external' or 'off', got "
                              f"{self.lifting!r}")
        if not self.live_lifting:
            self.lifting = "off"
        if self.env not in ("production", "development"):
            raise ConfigError(f"OCCUFLY_ENV must be 'production' or 'development', got {self.env!r}")
        if self.secret_key == DEFAULT_SECRET and self.env != "development":
            raise ConfigError(
                "OCCUFLY_SECRET_KEY is not set: the built-in secret is only allowed with "
                "OCCUFLY_ENV=development"
            )
        if len(self.secret_key) < 16:
            raise ConfigError("OCCUFLY_SECRET_KEY must be at least 16 characters")
        if not 0.0 <= self.quality_wait_s <= 600.0:
            raise ConfigError(f"OCCUFLY_QUALITY_WAIT_S must be 0 to 600 seconds, got "
                              f"{self.quality_wait_s!r}")

    @property
    def is_dev(self) -> bool:
        return self.env == "development"

    @property
    def workspaces_dir(self) -> Path:
        return self.data_dir / "scenes"

    @property
    def mask_store_dir(self) -> Path:
        return self.data_dir / "masks"

    @property
    def exports_dir(self) -> Path:
        return self.data_dir / "exports"

    @classmethod
    def from_env(cls, environ: dict[str, str] | None = None, **overrides) -> Settings:
        env = os.environ if environ is None else environ

        def num(name: str, default: float, kind=int):
            raw = env.get(name)
            if raw is None or raw == "":
                return default
            try:
                return kind(raw)
            except ValueError:
                raise ConfigError(f"{name} must be a number, got {raw!r}") from None

        data_dir = Path(env.get("OCCUFLY_DATA_DIR") or "data")
        roots = [Path(p) for p in (env.get("OCCUFLY_IMPORT_ROOTS") or "").split(os.pathsep) if p]
        kw: dict = dict(
            data_dir=data_dir,
            database_url=env.get("OCCUFLY_DATABASE_URL", ""),
            import_roots=roots,
            secret_key=env.get("OCCUFLY_SECRET_KEY") or DEFAULT_SECRET,
            env=env.get("OCCUFLY_ENV", "production"),
            dask_address=env.get("OCCUFLY_DASK_ADDRESS") or None,
            max_upload_bytes=int(num("OCCUFLY_MAX_UPLOAD_MB", 64, float) * 1024 * 1024),
            lease_seconds=int(num("OCCUFLY_LEASE_MINUTES", 30, float) * 60),
            session_seconds=int(num("OCCUFLY_SESSION_HOURS", 12, float) * 3600),
            fill_debounce_s=num("OCCUFLY_FILL_DEBOUNCE_S", 5.0, float),
            fill_settle_s=num("OCCUFLY_FILL_SETTLE_S", 120.0, float),
            quality_wait_s=num("OCCUFLY_QUALITY_WAIT_S", 1.5, float),
            fill_nice=num("OCCUFLY_FILL_NICE", 5),
            review_refresh_process=bool(num("OCCUFLY_REVIEW_REFRESH_PROCESS", 1)),
            review_refresh_nice=num("OCCUFLY_REVIEW_REFRESH_NICE", 10),
            min_independent_coverage=num("OCCUFLY_MIN_INDEPENDENT_COVERAGE", 0.5, float),
            job_workers=num("OCCUFLY_JOB_WORKERS", 2),
            job_processes=bool(num("OCCUFLY_JOB_PROCESSES", 1)),
            argon2_memory_kib=num("OCCUFLY_ARGON2_MEMORY_KIB", 65536),
            argon2_time_cost=num("OCCUFLY_ARGON2_TIME_COST", 3),
            lifting=env.get("OCCUFLY_LIFTING") or "embedded",
            auto_upgrade=bool(num("OCCUFLY_AUTO_UPGRADE", 1)),
            max_import_upload_bytes=int(num("OCCUFLY_MAX_IMPORT_UPLOAD_MB", 8192, float) * 2**20),
            export_keep_last=num("OCCUFLY_EXPORT_KEEP_LAST", 0),
            export_max_age_days=num("OCCUFLY_EXPORT_MAX_AGE_DAYS", 0.0, float),
            max_json_bytes=int(num("OCCUFLY_MAX_JSON_MB", 1, float) * 2**20),
            max_selection_bytes=int(num("OCCUFLY_MAX_SELECTION_MB", 64, float) * 2**20),
            max_correction_points=num("OCCUFLY_MAX_CORRECTION_POINTS", 2_000_000),
            user_quota_bytes=int(num("OCCUFLY_USER_QUOTA_MB", 2048, float) * 2**20),
            scene_quota_bytes=int(num("OCCUFLY_SCENE_QUOTA_MB", 10240, float) * 2**20),
            active_jobs_per_user=num("OCCUFLY_ACTIVE_JOBS_PER_USER", 4),
            export_quota_bytes=int(num("OCCUFLY_EXPORT_QUOTA_MB", 51200, float) * 2**20),
            viewer_sockets_per_user=num("OCCUFLY_VIEWER_SOCKETS_PER_USER", 4),
            open_review_items_per_user=num("OCCUFLY_OPEN_REVIEW_ITEMS_PER_USER", 500),
            comments_per_user_hour=num("OCCUFLY_COMMENTS_PER_USER_HOUR", 300),
            comments_per_item=num("OCCUFLY_COMMENTS_PER_ITEM", 500),
        )
        kw["trusted_proxies"] = [p.strip() for p in (env.get("OCCUFLY_TRUSTED_PROXIES") or "")
                                  .split(",") if p.strip()]
        kw["allowed_origins"] = [o.strip().rstrip("/") for o in
                                  (env.get("OCCUFLY_ALLOWED_ORIGINS") or "").split(",")
                                  if o.strip()]
        if env.get("OCCUFLY_FRONTEND_DIR"):
            kw["frontend_dir"] = Path(env["OCCUFLY_FRONTEND_DIR"])
        if env.get("OCCUFLY_DOCS_SITE_DIR"):
            kw["docs_site_dir"] = Path(env["OCCUFLY_DOCS_SITE_DIR"])
        kw.update(overrides)
        if not 0 <= kw["fill_nice"] <= 19:
            raise ConfigError(f"OCCUFLY_FILL_NICE must be 0..19 (added niceness), got "
                              f"{kw['fill_nice']}")
        if not 0 <= kw["review_refresh_nice"] <= 19:
            raise ConfigError(f"OCCUFLY_REVIEW_REFRESH_NICE must be 0..19 (added niceness), got "
                              f"{kw['review_refresh_nice']}")
        return cls(**kw)
