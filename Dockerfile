# The benchmark server: `docker build -t semantic3d-server .` then
#   docker run -p 127.0.0.1:8000:8000 -v semantic3d-data:/data semantic3d-server
# (SQLite with the embedded worker), or `docker compose up` for PostgreSQL (compose.yaml).
# docs/server.md, "Container", has the details.

FROM python:3.11-slim AS wheel
WORKDIR /src
COPY pyproject.toml README.md LICENSE ./
COPY src ./src
RUN pip wheel --no-cache-dir --no-deps --wheel-dir /wheels .

FROM python:3.11-slim
ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1 \
    SEMANTIC3D_DATA_DIR=/data
# Only what serving needs: the package with its `server` and `postgres` extras.
COPY --from=wheel /wheels /tmp/wheels
RUN pip install --no-cache-dir "$(ls /tmp/wheels/semantic3d-*.whl)[server,postgres]" \
    && rm -rf /tmp/wheels
# An unprivileged user owns the data folder; the server never runs as root.
RUN groupadd --system --gid 10001 semantic3d \
    && useradd --system --uid 10001 --gid 10001 --home-dir /data --no-create-home \
        --shell /usr/sbin/nologin semantic3d \
    && mkdir /data && chown 10001:10001 /data && chmod 0700 /data
USER 10001:10001
WORKDIR /data
VOLUME ["/data"]
EXPOSE 8000
HEALTHCHECK --interval=30s --timeout=5s --start-period=30s --retries=3 \
    CMD ["python", "-c", "import sys, urllib.request; sys.exit(urllib.request.urlopen('http://127.0.0.1:8000/api/health', timeout=4).status != 200)"]
CMD ["semantic3d", "serve", "--host", "0.0.0.0", "--port", "8000"]
