# syntax=docker/dockerfile:1
# The place-recognition service: the `serve` extra and the bundled default model, no torch.
#
#   docker build -t overlapmamba .
#   docker run --init --stop-timeout 60 -p 8000:8000 -v om-data:/data \
#       -e OVERLAPMAMBA_AUTH__KEYS='[...]' overlapmamba
#
# (--stop-timeout: the drain and the maps' snapshots outlast Docker's 10 s; --init: a signal
# during start-up, before the server handles its own, is not lost on PID 1.) The ENV below
# outranks a config file: set host, port, data_dir and model as variables, not in the file
# (serve warns when a variable overrides the file).
#
#   make image        # the same with podman (or docker), offline: a Debian bookworm base made
#                     # with debootstrap and the dependencies from a wheelhouse (deploy/image.py)
#
# Two stages: `build` makes a virtual environment; `runtime` copies only that and the model.
# Dependencies are installed before the source is copied, so editing code rebuilds one
# small layer; from deploy/wheelhouse when it holds wheels (no index is asked), else from
# PyPI. docs/deploy.md has the compose file, sizing and operations.

# Any Debian bookworm image with python3 (3.11) and its venv module: the official slim one,
# or the one `make image` makes from Debian's packages when no registry is reachable.
ARG PYTHON_IMAGE=python:3.11-slim-bookworm

FROM ${PYTHON_IMAGE} AS build
ENV PIP_DISABLE_PIP_VERSION_CHECK=1 \
    PYTHONDONTWRITEBYTECODE=1 \
    OVERLAPMAMBA_CACHE=/opt/overlapmamba \
    OVERLAPMAMBA_KERNEL_MARCH=x86-64-v2
# A C compiler for the selective-scan kernel (this stage only: the runtime has none). Not
# pinned: bookworm's gcc moves with point releases, and a pin would break the build then.
# hadolint ignore=DL3008
RUN apt-get update && apt-get install -y --no-install-recommends gcc libc6-dev \
    && rm -rf /var/lib/apt/lists/*
RUN python3 -m venv /opt/venv
ENV PATH=/opt/venv/bin:$PATH
WORKDIR /src
# 1. Dependencies: the `serve` extra's whole closure and the build backend, at the versions
#    of constraints.txt (the lock the suite passed with), each file checked against the
#    SHA-256 PyPI lists for it (deploy/requirements-serve.txt, written by `make lock`): from
#    the wheelhouse when it has wheels (an air-gapped build), else from the index. A file
#    that is not the one locked, or a wheelhouse holding another version, fails the build
#    rather than ship it.
COPY deploy/requirements-serve.txt ./
COPY deploy/wheelhouse /wheels
RUN if [ -n "$(find /wheels -name '*.whl' -print -quit)" ]; then \
      pip install --no-cache-dir --require-hashes --no-index --find-links /wheels \
        -r requirements-serve.txt; \
    else pip install --no-cache-dir --require-hashes -r requirements-serve.txt; fi
# 2. The source, without dependencies (they are all above), built by the setuptools installed
#    above (no build isolation: nothing is fetched, no build tool moves unasked).
COPY pyproject.toml README.md ./
COPY overlapmamba/__init__.py overlapmamba/__main__.py overlapmamba/py.typed ./overlapmamba/
COPY overlapmamba/cli ./overlapmamba/cli
COPY overlapmamba/core ./overlapmamba/core
COPY overlapmamba/service ./overlapmamba/service
RUN pip install --no-cache-dir --no-build-isolation --no-deps . \
    && python -c "import importlib.util as u, sys; sys.exit(u.find_spec('torch') is not None)" \
    && python -m overlapmamba.core.scan_kernel

FROM ${PYTHON_IMAGE} AS runtime
LABEL org.opencontainers.image.title="overlapmamba" \
      org.opencontainers.image.description="LiDAR place recognition service (OverlapMamba)" \
      org.opencontainers.image.licenses="MIT"
RUN groupadd --system --gid 10001 overlapmamba \
    && useradd --system --uid 10001 --gid overlapmamba --home-dir /data --no-create-home \
       --shell /usr/sbin/nologin overlapmamba \
    && mkdir /data \
    && chown overlapmamba:overlapmamba /data
COPY --from=build /opt/venv /opt/venv
COPY --from=build /opt/overlapmamba /opt/overlapmamba
COPY models/overlapmamba-hdl64.onnx /app/models/overlapmamba-hdl64.onnx
COPY deploy/healthcheck.py /app/healthcheck.py
ENV PATH=/opt/venv/bin:$PATH \
    PYTHONUNBUFFERED=1 \
    OVERLAPMAMBA_HOST=0.0.0.0 \
    OVERLAPMAMBA_PORT=8000 \
    OVERLAPMAMBA_DATA_DIR=/data \
    OVERLAPMAMBA_MODEL=/app/models/overlapmamba-hdl64.onnx \
    OVERLAPMAMBA_CACHE=/opt/overlapmamba \
    OVERLAPMAMBA_KERNEL_MARCH=x86-64-v2
WORKDIR /app
VOLUME ["/data"]
USER 10001:10001
EXPOSE 8000
# /readyz: 503 while maps replay, while Qdrant is unreachable and while draining.
HEALTHCHECK --interval=10s --timeout=5s --start-period=60s --retries=3 \
    CMD ["python", "/app/healthcheck.py"]
# SIGTERM drains requests in flight (up to limits.request_timeout_s, 30 s) and snapshots
# the maps: give `docker stop` more than that (--time 60; compose: stop_grace_period).
STOPSIGNAL SIGTERM
ENTRYPOINT ["overlapmamba"]
CMD ["serve"]
