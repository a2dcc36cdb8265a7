# eqgw: one image for the gateway (`eqgw serve`), the simulator (`eqgw simulate`) and the edge
# forwarder (`eqgw forward`). Build: docker build -t eqgw .
#
# Stage 1 builds the wheel (the package with its migrations, dashboard, DBC and scenarios);
# stage 2 installs only that wheel, with the versions of constraints.txt (what CI tested).

FROM python:3.11-slim AS build
ENV PIP_NO_CACHE_DIR=1 PIP_DISABLE_PIP_VERSION_CHECK=1
WORKDIR /src
COPY pyproject.toml README.md ./
COPY app ./app
COPY migrations ./migrations
COPY static ./static
RUN pip wheel --no-deps --wheel-dir /wheels .

FROM python:3.11-slim
ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1 \
    EQGW_API_HOST=0.0.0.0 \
    EQGW_API_PORT=8000
COPY --from=build /wheels /tmp/wheels
COPY constraints.txt /tmp/constraints.txt
RUN pip install -c /tmp/constraints.txt /tmp/wheels/*.whl \
    && rm -rf /tmp/wheels /tmp/constraints.txt \
    && useradd --system --home-dir /var/lib/eqgw --create-home eqgw

USER eqgw
WORKDIR /var/lib/eqgw
EXPOSE 8000 29536
# Healthy while /readyz answers 200 (database reachable and writable, a bus open). The
# simulator and the forwarder serve no HTTP: docker-compose.yml turns this off for them.
HEALTHCHECK --interval=10s --timeout=5s --start-period=60s --retries=3 \
    CMD python -c "import os, urllib.request as u; u.urlopen('http://127.0.0.1:%s/readyz' % os.environ.get('EQGW_API_PORT', '8000'), timeout=4)"
# SIGTERM starts the bounded shutdown; give it longer than its bound before SIGKILL
# (docker run --stop-timeout 60, or stop_grace_period in compose).
STOPSIGNAL SIGTERM
ENTRYPOINT ["eqgw"]
CMD ["serve"]
