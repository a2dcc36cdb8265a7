"""Shared pieces of the alert delivery tests: a real HTTP receiver and alert events written
straight into the outbox (no rule engine involved)."""

from __future__ import annotations

import itertools
import json
import threading
import time
from dataclasses import dataclass, field
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import Any

from sqlalchemy import Engine, insert, update

from eqgw.notify import repository as q
from eqgw.notify.webhooks import verify
from eqgw.store.models import Alert, AlertEvent

# The receivers here listen on loopback, which webhooks may not reach unless allowed.
ALLOW_LOOPBACK = "127.0.0.0/8"
SECRET = "s3cret-s3cret-s3cret"


@dataclass
class Request:
    headers: dict[str, str]
    body: bytes
    status: int

    @property
    def json(self) -> Any:
        return json.loads(self.body)


@dataclass
class Receiver:
    """A webhook receiver on 127.0.0.1: answers `status` (500 to fail), records every request,
    and accepts (2xx) each body it checked; it can be stopped and started on the same port."""

    secret: str
    status: int = 200
    port: int = 0
    reply: bytes = b"ok"
    delay_s: float = 0.0  # how long each answer takes
    requests: list[Request] = field(default_factory=list)
    bad_signatures: int = 0
    _server: ThreadingHTTPServer | None = None
    _thread: threading.Thread | None = None
    _lock: threading.Lock = field(default_factory=threading.Lock)

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}/hook"

    def start(self) -> Receiver:
        receiver = self

        class Handler(BaseHTTPRequestHandler):
            def do_POST(self) -> None:
                body = self.rfile.read(int(self.headers.get("Content-Length", "0")))
                if receiver.delay_s:
                    time.sleep(receiver.delay_s)
                headers = dict(self.headers.items())
                status = receiver.status
                with receiver._lock:
                    if not verify(receiver.secret, headers, body):
                        receiver.bad_signatures += 1
                        status = 401
                    receiver.requests.append(Request(headers, body, status))
                self.send_response(status)
                self.send_header("Content-Length", str(len(receiver.reply)))
                self.end_headers()
                self.wfile.write(receiver.reply)

            def log_message(self, *args: Any) -> None:
                pass

        self._server = ThreadingHTTPServer(("127.0.0.1", self.port), Handler)
        self.port = self._server.server_address[1]
        self._thread = threading.Thread(target=self._server.serve_forever, daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        if self._server is not None:
            self._server.shutdown()
            self._server.server_close()
            assert self._thread is not None
            self._thread.join(5)
            self._server = None

    def accepted(self) -> list[Any]:
        """Bodies answered with a 2xx, in arrival order."""
        with self._lock:
            return [r.json for r in self.requests if 200 <= r.status < 300]

    def attempts_for(self, event_id: int) -> int:
        with self._lock:
            return sum(1 for r in self.requests if r.json.get("event_id") == event_id)


_alerts: Any = Alert.__table__
_next_sa = itertools.count()
_events: Any = AlertEvent.__table__


def add_alert(
    engine: Engine,
    *,
    vehicle_id: str = "BUS-1",
    rule: str = "imbalance",
    severity: str = "warning",
    sa: int | None = None,
) -> dict[str, Any]:
    """An alert row (raised now), returned as the contract's `alert` object."""
    # One open alert per (unit, rule): each call gets its own unit unless told.
    sa = next(_next_sa) % 250 if sa is None else sa
    now = time.time()
    row = {
        "vehicle_id": vehicle_id,
        "bus": f"{vehicle_id}/can0",
        "sa": sa,
        "rule": rule,
        "severity": severity,
        "state": "active",
        "muted": False,
        "message": f"{rule} on {vehicle_id}",
        "values": {"b_minus_a_v": 0.62},
        "raised_at": now,
        "updated_at": now,
    }
    with engine.begin() as conn:
        alert_id = conn.execute(insert(_alerts).values(**row).returning(_alerts.c.id)).scalar_one()
    return {
        "id": alert_id,
        "vehicle_id": vehicle_id,
        "vehicle_name": f"Bus {vehicle_id}",
        "bus": row["bus"],
        "sa": sa,
        "rule": rule,
        "severity": severity,
        "state": "active",
        "message": row["message"],
        "values": row["values"],
        "raised_at": now,
        "acknowledged_at": None,
        "acknowledged_by": None,
        "ack_comment": None,
        "cleared_at": None,
    }


def add_event(engine: Engine, alert: dict[str, Any], kind: str, *, muted: bool = False) -> int:
    """Append an alert event as the alert engine does; returns its id."""
    now = time.time()
    state = {"raised": "active", "acknowledged": "acknowledged", "cleared": "cleared"}[kind]
    payload = {"event": kind, "ts": now, "alert": {**alert, "state": state}}
    with engine.begin() as conn:
        event_id: int = conn.execute(
            insert(_events)
            .values(alert_id=alert["id"], kind=kind, ts=now, payload=payload, muted=muted)
            .returning(_events.c.id)
        ).scalar_one()
        if kind == "cleared":  # the alert row too, in the same transaction
            conn.execute(
                update(_alerts)
                .where(_alerts.c.id == alert["id"])
                .values(state="cleared", cleared_at=now, updated_at=now)
            )
    return event_id


def make_hook(engine: Engine, url: str, **kw: Any) -> int:
    now = time.time()
    row = {
        "name": kw.pop("name", "ops"),
        "url": url,
        "secret": SECRET,
        "format": "json",
        "enabled": True,
        "created_at": now,
        "updated_at": now,
        **kw,
    }
    with engine.begin() as conn:
        return q.create_webhook(conn, row)


def deliveries(engine: Engine, webhook_id: int) -> list[dict[str, Any]]:
    with engine.begin() as conn:
        return q.list_deliveries(conn, webhook_id, limit=1000)
