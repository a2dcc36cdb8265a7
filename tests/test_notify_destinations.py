"""Email, Microsoft Teams and PagerDuty destinations: the webhook outbox's guarantees (every
event once, in order, nothing lost across a restart while the destination was down), its
filters, against a real SMTP server on loopback (aiosmtpd, STARTTLS with login and implicit
TLS, a self-signed certificate) and local HTTP receivers; on SQLite and PostgreSQL."""

from __future__ import annotations

import datetime
import gc
import ipaddress
import json
import ssl
import threading
import warnings
from collections.abc import Iterator
from dataclasses import dataclass, field
from email import message_from_bytes
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import Any

import httpx
import pytest
from sqlalchemy import Engine

from eqgw.config import Settings, SmtpSettings
from eqgw.main import create_app
from eqgw.notify.delivery import AlertDelivery
from eqgw.web.settings import ApiSettings
from tests.api_helpers import lifespan, wait_for
from tests.proc_helpers import free_port
from tests.test_webhooks import PUBLIC, _async, fast
from tests.webhook_helpers import ALLOW_LOOPBACK, add_alert, add_event, deliveries, make_hook

aiosmtpd = pytest.importorskip("aiosmtpd")
from aiosmtpd.controller import Controller  # noqa: E402
from aiosmtpd.smtp import AuthResult, LoginPassword  # noqa: E402

ROUTING_KEY = "R0UT1NGKEY0123456789abcdefABCDEF"


@pytest.fixture(scope="module")
def cert(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """A self-signed certificate for 127.0.0.1 and its key."""
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import NameOID

    key = ec.generate_private_key(ec.SECP256R1())
    name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "127.0.0.1")])
    now = datetime.datetime.now(datetime.UTC)
    crt = (
        x509.CertificateBuilder()
        .subject_name(name)
        .issuer_name(name)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - datetime.timedelta(days=1))
        .not_valid_after(now + datetime.timedelta(days=1))
        .add_extension(
            x509.SubjectAlternativeName([x509.IPAddress(ipaddress.ip_address("127.0.0.1"))]),
            critical=False,
        )
        .add_extension(x509.BasicConstraints(ca=True, path_length=None), critical=True)
        .sign(key, hashes.SHA256())
    )
    d = tmp_path_factory.mktemp("cert")
    (d / "cert.pem").write_bytes(crt.public_bytes(serialization.Encoding.PEM))
    (d / "key.pem").write_bytes(
        key.private_bytes(
            serialization.Encoding.PEM,
            serialization.PrivateFormat.PKCS8,
            serialization.NoEncryption(),
        )
    )
    return d / "cert.pem", d / "key.pem"


@dataclass
class Mailbox:
    """What the SMTP server accepted: (from, to, message, over TLS, authenticated)."""

    messages: list[tuple[str, list[str], Any, bool, bool]] = field(default_factory=list)

    async def handle_DATA(self, server: Any, session: Any, envelope: Any) -> str:
        msg = message_from_bytes(envelope.content)
        tls = server.transport.get_extra_info("ssl_object") is not None
        authed = bool(session.authenticated)
        self.messages.append((envelope.mail_from, list(envelope.rcpt_tos), msg, tls, authed))
        return "250 OK"


def _authenticator(server: Any, session: Any, envelope: Any, mechanism: str, data: Any) -> Any:
    ok = isinstance(data, LoginPassword) and (data.login, data.password) == (b"eqgw", b"pw")
    return AuthResult(success=ok)


def _smtp_server(mode: str, cert: tuple[Path, Path], port: int, box: Mailbox) -> Controller:
    ctx = ssl.create_default_context(ssl.Purpose.CLIENT_AUTH)
    ctx.load_cert_chain(str(cert[0]), str(cert[1]))
    if mode == "starttls":
        return Controller(
            box, hostname="127.0.0.1", port=port, tls_context=ctx, require_starttls=True,
            authenticator=_authenticator, auth_require_tls=True,
        )  # fmt: skip
    return Controller(
        box, hostname="127.0.0.1", port=port, ssl_context=ctx,
        authenticator=_authenticator, auth_require_tls=False,
    )  # fmt: skip


def _delivery(engine: Engine, smtp: SmtpSettings | None = None, **delivery: Any) -> AlertDelivery:
    config = Settings(
        database_url="sqlite://",
        delivery=fast(**delivery),
        webhook_allow_networks=ALLOW_LOOPBACK,
        smtp=smtp or SmtpSettings(),
    )
    return AlertDelivery(engine, config, PUBLIC)


@pytest.mark.parametrize("mode", ["starttls", "tls"])
async def test_email_every_event_once_in_order_across_a_restart(
    engine: Engine, cert: tuple[Path, Path], mode: str
) -> None:
    port = free_port()
    smtp = SmtpSettings(
        host="127.0.0.1", port=port, tls=mode, username="eqgw", password="pw",
        sender="eqgw@example.org", ca_file=str(cert[0]),
    )  # fmt: skip
    hook = make_hook(engine, "mailto:ops@example.org,duty@example.org", format="email")
    alert = add_alert(engine, severity="critical")
    first = [add_event(engine, alert, "raised"), add_event(engine, alert, "acknowledged")]
    # The mail server is down: attempts fail and wait in the outbox.
    gw = _delivery(engine, smtp)
    await gw.start()
    try:

        async def failing() -> bool:
            rows = deliveries(engine, hook)
            return any(r["attempts"] >= 2 and r["last_error"] for r in rows)

        await wait_for(failing, what="failed attempts while the SMTP server is down")
    finally:
        await gw.stop()
    # Restarted, the server up, one more event: each arrives once, in event order.
    later = add_event(engine, alert, "cleared")
    box = Mailbox()
    server = _smtp_server(mode, cert, port, box)
    server.start()
    gw = _delivery(engine, smtp)
    await gw.start()
    try:
        await wait_for(lambda: _async(len(box.messages) >= 3), what="three emails")
        await wait_for(
            lambda: _async({r["state"] for r in deliveries(engine, hook)} == {"delivered"}),
            what="every delivery recorded as delivered",
        )
    finally:
        await gw.stop()
        server.stop()
    assert [m[2]["X-Eqgw-Event-Id"] for m in box.messages] == [str(e) for e in [*first, later]]
    for sender, to, msg, tls, authed in box.messages:
        assert sender == "eqgw@example.org" and to == ["ops@example.org", "duty@example.org"]
        assert tls and authed
        assert msg["To"] == "ops@example.org, duty@example.org"
    subjects = [m[2]["Subject"] for m in box.messages]
    assert subjects == [
        f"[eqgw] CRITICAL imbalance {kind} on Bus BUS-1"
        for kind in ("raised", "acknowledged", "cleared")
    ]
    text = box.messages[0][2].get_payload(decode=True).decode()
    assert alert["message"] in text and f"{PUBLIC}/#/vehicle/BUS-1" in text
    rows = deliveries(engine, hook)
    assert len(rows) == 3 and all(r["state"] == "delivered" for r in rows)


async def test_email_refused_login_is_retried_not_lost(
    engine: Engine, cert: tuple[Path, Path]
) -> None:
    """A wrong password fails the attempt, and the event waits in the outbox (the delivery
    bound, 1.5 s here, ends the attempt where the server holds its answer)."""
    port = free_port()
    box = Mailbox()
    server = _smtp_server("starttls", cert, port, box)
    server.start()
    smtp = SmtpSettings(
        host="127.0.0.1", port=port, username="eqgw", password="wrong", ca_file=str(cert[0])
    )
    hook = make_hook(engine, "mailto:ops@example.org", format="email")
    add_event(engine, add_alert(engine), "raised")
    gw = _delivery(engine, smtp, timeout_s=1.5)
    await gw.start()
    try:

        async def refused() -> Any:
            rows = deliveries(engine, hook)
            return rows and rows[0]["last_error"] and rows[0]

        row = await wait_for(refused, what="a refused login recorded")
    finally:
        await gw.stop()
        server.stop()
        # The tarpitted session's socket and transport are left to the collector when the
        # server's loop stops: collect them here, where their ResourceWarning is expected,
        # not during the next test's setup.
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", ResourceWarning)
            gc.collect()
    assert row["state"] == "pending" and row["delivered_at"] is None, row
    # aiosmtpd holds its 535 answer back (a tarpit): the attempt ends at its bound, or on
    # the 535 where a server answers at once.
    assert row["last_error"].startswith(
        ("SMTP 535", "TimeoutError", "no complete answer", "SMTPServerDisconnected")
    )
    assert box.messages == []


class _Json:
    """A local HTTP receiver of JSON bodies (answers `status`), by path."""

    def __init__(self, status: int = 202) -> None:
        self.status = status
        self.bodies: dict[str, list[Any]] = {}
        receiver = self

        class Handler(BaseHTTPRequestHandler):
            def do_POST(self) -> None:
                data = self.rfile.read(int(self.headers.get("Content-Length", "0")))
                receiver.bodies.setdefault(self.path, []).append(json.loads(data))
                self.send_response(receiver.status)
                self.send_header("Content-Length", "2")
                self.end_headers()
                self.wfile.write(b"{}")

            def log_message(self, *args: Any) -> None:
                pass

        self.server = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.url = f"http://127.0.0.1:{self.server.server_address[1]}"
        self.thread = threading.Thread(target=self.server.serve_forever, daemon=True)
        self.thread.start()

    def close(self) -> None:
        self.server.shutdown()
        self.server.server_close()
        self.thread.join(5)


@pytest.fixture
def receiver() -> Iterator[_Json]:
    r = _Json()
    try:
        yield r
    finally:
        r.close()


async def test_teams_and_pagerduty_with_filters(engine: Engine, receiver: _Json) -> None:
    teams = make_hook(engine, f"{receiver.url}/teams", name="teams", format="teams")
    pd = make_hook(engine, f"{receiver.url}/pd", name="pd", format="pagerduty", secret=ROUTING_KEY)
    # The same filters as any webhook: this one takes critical alerts only.
    make_hook(
        engine, f"{receiver.url}/pd-critical", name="pd critical", format="pagerduty",
        secret=ROUTING_KEY, min_severity="critical",
    )  # fmt: skip
    alert = add_alert(engine, severity="warning")
    events = [add_event(engine, alert, k) for k in ("raised", "acknowledged", "cleared")]
    gw = _delivery(engine)
    await gw.start()
    try:

        async def done() -> bool:
            return all(
                {r["state"] for r in deliveries(engine, h)} == {"delivered"}
                and len(deliveries(engine, h)) == 3
                for h in (teams, pd)
            )

        await wait_for(done, what="teams and pagerduty deliveries")
    finally:
        await gw.stop()
    assert "/pd-critical" not in receiver.bodies
    cards = receiver.bodies["/teams"]
    assert len(cards) == 3
    card = cards[0]["attachments"][0]
    assert cards[0]["type"] == "message"
    assert card["contentType"] == "application/vnd.microsoft.card.adaptive"
    content = card["content"]
    assert content["type"] == "AdaptiveCard"
    assert content["body"][0]["text"] == "WARNING imbalance raised on Bus BUS-1"
    facts = {f["title"]: f["value"] for f in content["body"][2]["facts"]}
    assert facts["Event"] == str(events[0]) and facts["Values"] == "b_minus_a_v 0.62"
    assert content["actions"][0]["url"] == f"{PUBLIC}/#/vehicle/BUS-1"
    pages = receiver.bodies["/pd"]
    assert [p["event_action"] for p in pages] == ["trigger", "acknowledge", "resolve"]
    assert {p["dedup_key"] for p in pages} == {f"eqgw-alert-{alert['id']}"}
    assert {p["routing_key"] for p in pages} == {ROUTING_KEY}
    trigger = pages[0]["payload"]
    assert trigger["severity"] == "warning" and trigger["source"] == "Bus BUS-1"
    assert trigger["summary"].startswith("WARNING imbalance raised on Bus BUS-1: ")
    assert "payload" not in pages[1] and "payload" not in pages[2]


async def test_destinations_through_the_api(db_url: str, cert: tuple[Path, Path]) -> None:
    """Created and checked like any webhook; the "send test" action mails; a URL that does not
    suit the format, or a host outside the destination policy, is refused (422)."""
    port = free_port()
    box = Mailbox()
    server = _smtp_server("starttls", cert, port, box)
    server.start()
    smtp = SmtpSettings(
        host="127.0.0.1", port=port, username="eqgw", password="pw", ca_file=str(cert[0])
    )
    keys: list[str] = []
    app = create_app(
        Settings(
            database_url=db_url, delivery=fast(), webhook_allow_networks=ALLOW_LOOPBACK, smtp=smtp
        ),
        api=ApiSettings(public_url="http://depot.example"),
        on_first_key=keys.append,
    )
    try:
        async with lifespan(app):
            transport = httpx.ASGITransport(app=app)
            async with httpx.AsyncClient(transport=transport, base_url="http://test") as c:
                admin = {"Authorization": f"Bearer {keys[0]}"}
                w = "/api/v1/webhooks"
                r = await c.post(
                    w, json={"name": "mail", "url": "mailto:ops@example.org", "format": "email"},
                    headers=admin,
                )  # fmt: skip
                assert r.status_code == 201, r.text
                hook = r.json()
                assert hook["format"] == "email" and hook["url"] == "mailto:ops@example.org"
                t = await c.post(f"{w}/{hook['id']}/test", headers=admin)
                assert t.status_code == 200 and t.json()["delivered"] is True, t.text
                assert [m[1] for m in box.messages] == [["ops@example.org"]]
                assert box.messages[0][2]["Subject"] == "[eqgw] INFO test test on Test vehicle"

                refused = [
                    {"name": "a", "url": "https://example.org/x", "format": "email"},
                    {"name": "b", "url": "mailto:ops@example.org", "format": "json"},
                    {"name": "c", "url": "mailto:not-an-address", "format": "email"},
                    {"name": "d", "url": "https://events.example.org/v2/enqueue",
                     "format": "pagerduty"},  # no routing key
                    {"name": "e", "url": "http://10.1.2.3/teams", "format": "teams"},
                ]  # fmt: skip
                for body in refused:
                    r = await c.post(w, json=body, headers=admin)
                    assert r.status_code == 422, (body, r.text)
                r = await c.patch(f"{w}/{hook['id']}", json={"format": "teams"}, headers=admin)
                assert r.status_code == 422 and "mailto" in r.text
    finally:
        server.stop()


@pytest.mark.postgres
@pytest.mark.slow
def test_two_gateway_processes_mail_every_event_once_in_order(
    pg_url: str, tmp_path: Path, cert: tuple[Path, Path]
) -> None:
    """Two `eqgw serve` processes on one PostgreSQL, the mail server down while events pile up
    and both retry them, then up: each event is mailed once, in event order."""
    from eqgw.store.engine import create_engine
    from eqgw.store.migrate import upgrade_engine
    from tests.cluster_helpers import readyz, start_gateway
    from tests.proc_helpers import wait_until
    from tests.test_webhooks_processes import DELIVERY

    engine = create_engine(pg_url)
    upgrade_engine(engine)
    port = free_port()
    fleet = tmp_path / "fleet.toml"
    fleet.write_text(DELIVERY)
    env = {
        "EQGW_SMTP__HOST": "127.0.0.1",
        "EQGW_SMTP__PORT": str(port),
        "EQGW_SMTP__USERNAME": "eqgw",
        "EQGW_SMTP__PASSWORD": "pw",
        "EQGW_SMTP__SENDER": "eqgw@example.org",
        "EQGW_SMTP__CA_FILE": str(cert[0]),
    }
    gateways = [start_gateway(tmp_path, pg_url, fleet, f"mail-{n}", extra_env=env) for n in (1, 2)]
    box = Mailbox()
    server = _smtp_server("starttls", cert, port, box)
    started = False
    try:
        for _, base in gateways:
            wait_until(lambda b=base: (readyz(b) or {}).get("ready"), 60, f"{base} ready")
        hook = make_hook(engine, "mailto:ops@example.org", format="email")
        ids: list[int] = []
        for n in range(6):
            alert = add_alert(engine, vehicle_id=f"BUS-{n}")
            ids += [add_event(engine, alert, "raised"), add_event(engine, alert, "cleared")]

        def retrying() -> bool:
            rows = deliveries(engine, hook)
            return len(rows) == len(ids) and any(r["attempts"] >= 2 for r in rows)

        wait_until(retrying, 60, "every event queued and retried while the server is down")
        server.start()
        started = True
        wait_until(lambda: len(box.messages) >= len(ids), 60, "every event mailed")
        wait_until(
            lambda: {r["state"] for r in deliveries(engine, hook)} == {"delivered"},
            30,
            "every delivery recorded",
        )
    finally:
        for proc, _ in gateways:
            proc.stop()
        if started:
            server.stop()
        engine.dispose()
    assert [m[2]["X-Eqgw-Event-Id"] for m in box.messages] == [str(i) for i in ids]


def test_teams_urls_are_shown_without_their_credentials() -> None:
    from eqgw.notify.destinations import redact_url

    workflow = (
        "https://prod-12.westeurope.logic.azure.com/workflows/abc/triggers/manual/paths/invoke"
        "?api-version=2016-06-01&sig=SECRETSIG"
    )
    assert "SECRETSIG" not in redact_url(workflow, "teams")
    connector = "https://example.org/webhookb2/abc/IncomingWebhook/123/SECRETID"
    assert (
        redact_url(connector, "teams")
        == "https://example.org/webhookb2/abc/IncomingWebhook/123/***"
    )
