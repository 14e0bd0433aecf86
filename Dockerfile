# OccuFly Studio web app + pipeline. Build: docker build -t occufly .
FROM python:3.11-slim-bookworm

ENV PYTHONDONTWRITEBYTECODE=1 PYTHONUNBUFFERED=1 PIP_NO_CACHE_DIR=1 \
    OCCUFLY_DATA_DIR=/data
# Open3D's shared-library needs; curl for the health check
RUN apt-get update \
 && apt-get install -y --no-install-recommends libusb-1.0-0 libgl1 libgomp1 curl \
 && rm -rf /var/lib/apt/lists/*

WORKDIR /opt/occufly
COPY pyproject.toml README.md* requirements.lock ./
# dependencies only from the hash-pinned lock (scripts/lock.sh: core, dev and masks extras),
# then the package itself without resolving anything
RUN pip install --require-hashes -r requirements.lock
COPY occufly ./occufly
COPY app ./app
COPY migrations ./migrations
COPY alembic.ini ./
COPY frontend ./frontend
RUN pip install --no-deps . && useradd --create-home --uid 1000 occufly && mkdir -p /data \
 && chown occufly /data
USER occufly
# the compiled kernels (denoise k-NN, robust vote decision, label splats, free-space depth rasters) into the user's numba cache
RUN python -c "import occufly.lifting.blockknn as k, occufly.lifting.robust as r, occufly.splat as s, occufly.densify.depthraster as d; k.compile_kernels(); s.compile_kernels(); d.compile_kernels(); r.compile_kernels()"
VOLUME ["/data"]
EXPOSE 8000
HEALTHCHECK --interval=15s --timeout=5s --start-period=30s --retries=5 \
  CMD curl -fsS http://127.0.0.1:8000/api/health || exit 1
# The app upgrades the database schema (Alembic) at start-up.
CMD ["occufly", "serve", "--host", "0.0.0.0", "--port", "8000"]
