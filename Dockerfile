# eqgw: one image for the gateway (`eqgw serve`), the simulator (`eqgw simulate`) and the edge
# forwarder (`eqgw forward`). Build: docker build -t eqgw .
FROM python:3.11-slim

ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1 \
    EQGW_API_HOST=0.0.0.0 \
    EQGW_API_PORT=8000

WORKDIR /opt/eqgw
# The package finds migrations/ and static/ beside app/, so it is installed in place.
COPY pyproject.toml README.md alembic.ini ./
COPY app ./app
COPY migrations ./migrations
COPY static ./static
RUN pip install -e . \
    && useradd --system --home-dir /var/lib/eqgw --create-home eqgw

USER eqgw
WORKDIR /var/lib/eqgw
EXPOSE 8000 29536
ENTRYPOINT ["eqgw"]
CMD ["serve"]
