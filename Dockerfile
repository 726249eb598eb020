# syntax=docker/dockerfile:1
#
# thermal-edge: the edge service in a container. SocketCAN interfaces live in the host's network
# namespace, so run it with --network host (the metrics then bind the host's 127.0.0.1:9108):
#
#   docker build -t thermal-edge .
#   docker run -d --name thermal-edge --network host --restart on-failure \
#     -v /etc/thermal-edge:/etc/thermal-edge:ro -v thermal-edge-state:/var/lib/thermal-edge \
#     thermal-edge
#
# The image carries a default /etc/thermal-edge/edge.yaml (`thermal-edge config example`: can0, the
# packaged pm10kw model by name); mount the drive's own directory over it (its edge.yaml names a
# model file beside it or a packaged model). Simulated machine and demo: deploy/compose.yaml.

ARG PYTHON_IMAGE=python:3.11-slim-bookworm

# ---- build: the same wheel the tests install (pip wheel of this repository) + its dependencies;
# the package data (DBC, machine models, drive cycles, example edge.yaml) is inside the wheel
FROM ${PYTHON_IMAGE} AS build
WORKDIR /src
COPY pyproject.toml README.md LICENSE ./
COPY thermal_edge ./thermal_edge
RUN pip wheel --no-cache-dir --wheel-dir /wheels .

# ---- runtime
FROM ${PYTHON_IMAGE}
LABEL org.opencontainers.image.title="thermal-edge" \
      org.opencontainers.image.description="Online-adapted LPTN thermal protection for PM machines: CAN in, derating out." \
      org.opencontainers.image.licenses="Apache-2.0"

ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    OPENBLAS_NUM_THREADS=1 \
    OMP_NUM_THREADS=1 \
    VIRTUAL_ENV=/opt/thermal-edge \
    PATH=/opt/thermal-edge/bin:$PATH \
    THERMAL_EDGE_METRICS_PORT=9108

# The venv under /opt/thermal-edge (as on a systemd install), from the wheels only.
RUN --mount=type=bind,from=build,source=/wheels,target=/wheels \
    python -m venv /opt/thermal-edge \
 && /opt/thermal-edge/bin/pip install --no-cache-dir --no-index --find-links /wheels /wheels/thermal_edge-*.whl

# /etc/thermal-edge/edge.yaml from the wheel (checked as the service reads it), an unprivileged
# user and its state directory.
RUN install -d -m 0755 /etc/thermal-edge \
 && thermal-edge config example > /etc/thermal-edge/edge.yaml \
 && thermal-edge run --check --config /etc/thermal-edge/edge.yaml \
 && useradd --system --no-log-init --uid 10001 --user-group --home-dir /var/lib/thermal-edge \
      --no-create-home --shell /usr/sbin/nologin thermal-edge \
 && install -d -o 10001 -g 10001 -m 0750 /var/lib/thermal-edge

# /etc/thermal-edge: edge.yaml + machines/ (read only); /var/lib/thermal-edge: the persisted
# parameters, adaptation decisions and thermal state (keep it across container restarts).
VOLUME ["/etc/thermal-edge", "/var/lib/thermal-edge"]
USER 10001:10001
WORKDIR /var/lib/thermal-edge

# Prometheus metrics (read only). The configuration binds 127.0.0.1: with --network host that
# is the host's loopback; put a reverse proxy in front to expose it further.
EXPOSE 9108

# healthy = the metrics endpoint answers (no curl in slim: Python's urllib)
HEALTHCHECK --interval=30s --timeout=5s --start-period=60s --retries=3 \
  CMD ["python", "-c", "import os, urllib.request; urllib.request.urlopen('http://127.0.0.1:%s/metrics' % os.environ.get('THERMAL_EDGE_METRICS_PORT', '9108'), timeout=4).read()"]

# SIGTERM (docker stop) saves the state and exits 0; allow it the time (docker stop -t 30).
STOPSIGNAL SIGTERM
ENTRYPOINT ["thermal-edge"]
CMD ["run", "--config", "/etc/thermal-edge/edge.yaml"]
