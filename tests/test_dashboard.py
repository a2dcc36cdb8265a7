"""The dashboard end to end: Debian's chromium driven by Playwright against the real gateway
(uvicorn in a thread) with a simulated fleet on a temporary SQLite database.

Every wait is Playwright's auto-waiting `expect` with generous timeouts; nothing asserts timing.
Screenshots of the overview, a vehicle page, the alerts and a parked vehicle go to a temporary
folder; `EQGW_SCREENSHOTS=docs/screenshots` makes them the README's (a run never changes the
checkout unless asked to).
"""

from __future__ import annotations

import asyncio
import os
import re
import shutil
import socket
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest

pytestmark = pytest.mark.browser

CHROMIUM = "/usr/bin/chromium"
if shutil.which(CHROMIUM) is None:
    pytest.skip(f"no chromium at {CHROMIUM} (apt-get install -y chromium)", allow_module_level=True)
sync_api = pytest.importorskip(
    "playwright.sync_api", reason="playwright is not installed (pip install playwright)"
)
Page = sync_api.Page
expect = sync_api.expect

import uvicorn  # noqa: E402

from eqgw.bus.config import BusConfig  # noqa: E402
from eqgw.bus.reader import BusReader  # noqa: E402
from eqgw.bus.writer import BusWriter  # noqa: E402
from eqgw.config import Settings  # noqa: E402
from eqgw.main import create_app  # noqa: E402
from eqgw.sim.clock import RealtimeClock  # noqa: E402
from eqgw.sim.fleet import SimulatedFleet  # noqa: E402
from eqgw.web.settings import ApiSettings  # noqa: E402
from tests.support import web  # noqa: E402

SCREENSHOTS = Path(
    os.environ.get("EQGW_SCREENSHOTS") or Path(tempfile.gettempdir()) / "eqgw-screenshots"
)
CHROMIUM_ARGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
]
LONG = 60_000  # ms: shared CI cores, a simulator fault timer of 10 s, command resends of 1 s
VEHICLES = 4


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port: int = s.getsockname()[1]
        return port


@dataclass
class Gateway:
    """`eqgw serve --simulate` in-process: uvicorn on its own loop in a thread."""

    base: str
    sim: SimulatedFleet
    loop: asyncio.AbstractEventLoop
    admin: str
    keys: dict[str, str] = field(default_factory=dict)
    app: Any = None

    def call(self, fn: Callable[..., Any], *args: Any) -> None:
        """Run `fn` on the gateway's loop (the simulator is not thread-safe)."""
        self.loop.call_soon_threadsafe(fn, *args)

    def key(self, role: str) -> str:
        if role not in self.keys:
            r = web.post(
                f"{self.base}/api/v1/keys",
                json={"name": f"{role} (browser test)", "role": role},
                headers={"Authorization": f"Bearer {self.admin}"},
            )
            assert r.status_code == 201, r.text
            self.keys[role] = r.json()["key"]
        return self.keys[role]

    def login_code(self, key: str, ttl_s: float = 600) -> str:
        """A one-time login code of `key`, as `eqgw keys login-link` makes one."""
        from eqgw.security import repository as q
        from eqgw.security.keys import hash_key
        from eqgw.security.login_codes import create_login_code

        engine = self.app.state.rt.engine
        with engine.connect() as conn:
            row = q.key_by_hash(conn, hash_key(key))
        assert row is not None
        with engine.begin() as conn:  # writes first: waits for SQLite's write lock
            code: str = create_login_code(conn, int(row["id"]), ttl_s)
        return code


@pytest.fixture(scope="module")
def gateway(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Gateway]:
    with run_gateway(tmp_path_factory, VEHICLES) as gw:
        yield gw


@contextmanager
def run_gateway(
    tmp_path_factory: pytest.TempPathFactory,
    vehicles: int,
    *,
    config: dict[str, Any] | None = None,
    port: int | None = None,
) -> Iterator[Gateway]:
    """The gateway with `vehicles` simulated ones, every unit heard before it is handed out
    (`config`: more gateway settings; `port`: where it listens, else a free one)."""
    db = tmp_path_factory.mktemp("dashboard") / "eqgw.db"
    sim = SimulatedFleet(vehicles, seed=1, clock=RealtimeClock())
    first: list[str] = []
    port = port or _free_port()
    app = create_app(
        Settings(database_url=f"sqlite:///{db}", **(config or {})),
        api=ApiSettings(port=port),
        sim=sim,
        on_first_key=first.append,
    )
    server = uvicorn.Server(
        uvicorn.Config(
            app, host="127.0.0.1", port=port, log_level="warning", ws="websockets-sansio"
        )
    )
    loop = asyncio.new_event_loop()
    thread = threading.Thread(
        target=loop.run_until_complete, args=(server.serve(),), name="gateway", daemon=True
    )
    thread.start()
    deadline = time.monotonic() + 60
    while not server.started:
        assert thread.is_alive(), "the gateway did not start"
        assert time.monotonic() < deadline, "the gateway did not start within 60 s"
        time.sleep(0.05)
    gw = Gateway(f"http://127.0.0.1:{port}", sim, loop, first[0], app=app)
    # Wait until every simulated unit is heard, so tiles start with numbers.
    while True:
        r = web.get(f"{gw.base}/api/v1/vehicles", headers={"Authorization": f"Bearer {gw.admin}"})
        units = [u for v in r.json()["vehicles"] for u in v["units"]]
        if len(r.json()["vehicles"]) >= vehicles and units and all(u["v12"] for u in units):
            break
        assert time.monotonic() < deadline, "the simulated fleet was not heard within 60 s"
        time.sleep(0.2)
    try:
        yield gw
    finally:
        server.should_exit = True
        thread.join(timeout=60)
        loop.close()


@pytest.fixture(scope="module")
def browser() -> Iterator[Any]:
    with sync_api.sync_playwright() as p:
        b = p.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        yield b
        b.close()


@pytest.fixture
def page(browser: Any) -> Iterator[Page]:
    context = browser.new_context(viewport={"width": 1280, "height": 900})
    pg = context.new_page()
    errors: list[str] = []
    pg.on("pageerror", lambda exc: errors.append(str(exc)))
    yield pg
    context.close()
    assert not errors, f"JavaScript errors on the page: {errors}"


def login_by_url(page: Page, gw: Gateway, key: str, hash_: str = "") -> None:
    """Log in as `key` the way an operator does: a one-time login link, confirmed."""
    page.goto(f"{gw.base}/#login={gw.login_code(key)}")
    page.get_by_role("button", name="Sign in").click()
    expect(page.locator(".topbar")).to_be_visible(timeout=LONG)
    if hash_:
        page.goto(f"{gw.base}/{hash_}")
    expect(page.locator("#conn")).to_have_attribute("data-state", "live", timeout=LONG)


def assert_no_horizontal_overflow(page: Page, width: int) -> None:
    """At `width` px the page fits without a sideways scrollbar (charts resize on their own)."""
    page.set_viewport_size({"width": width, "height": 900})
    page.wait_for_function(
        "document.documentElement.scrollWidth <= document.documentElement.clientWidth",
        timeout=LONG,
    )


def test_login_form_refuses_bad_key_and_logout_forgets(page: Page, gateway: Gateway) -> None:
    page.goto(gateway.base + "/")
    page.get_by_label("API key").fill("eqgw_not_a_key")
    page.get_by_role("button", name="Log in").click()
    expect(page.locator("#login-error")).to_contain_text("unknown or revoked", timeout=LONG)
    page.get_by_label("API key").fill(gateway.key("viewer"))
    page.get_by_label("API key").press("Enter")
    expect(page.locator("#who")).to_contain_text("viewer", timeout=LONG)
    expect(page.locator(".tile")).to_have_count(VEHICLES, timeout=LONG)
    page.get_by_role("button", name="Log out").click()
    expect(page.get_by_label("API key")).to_be_visible()
    assert page.evaluate("localStorage.getItem('eqgw.key')") is None
    page.reload()
    expect(page.get_by_label("API key")).to_be_visible(timeout=LONG)


def test_overview_live_fault_filters_and_layout(page: Page, gateway: Gateway) -> None:
    login_by_url(page, gateway, gateway.admin)
    assert "key=" not in page.url and "login=" not in page.url, "the code must leave the address"
    expect(page.locator(".tile")).to_have_count(VEHICLES, timeout=LONG)
    tile = page.locator('.tile[data-vehicle="SIM-002"]')
    expect(tile.locator('[data-field="v12"]').first).to_have_text(re.compile(r"^\d+\.\d\d V$"))
    expect(tile.locator(".state")).to_have_text("Online")
    # The alerts page shows once the API has /api/v1/alerts (feature-detected).
    expect(page.locator("#nav-alerts")).to_be_visible()

    # A fault injected in the simulator reaches the tile without a reload, worst first.
    page.evaluate("window.__noReload = true")
    gateway.call(gateway.sim.fail_equalizer, "SIM-002")
    expect(tile.locator('[data-fault="EQFLT"]')).to_be_visible(timeout=LONG)
    expect(page.locator(".tile").first).to_have_attribute("data-vehicle", "SIM-002", timeout=LONG)
    assert page.evaluate("window.__noReload") is True

    page.get_by_label("Needs attention only").check()
    expect(page.locator(".tile")).not_to_have_count(VEHICLES, timeout=LONG)
    expect(tile).to_be_visible()
    page.get_by_label("Needs attention only").uncheck()
    expect(page.locator(".tile")).to_have_count(VEHICLES)
    page.get_by_label("Depot / group").select_option("simulated")
    expect(page.locator(".tile")).to_have_count(VEHICLES)

    for width in (1024, 1920):
        assert_no_horizontal_overflow(page, width)
    page.set_viewport_size({"width": 1280, "height": 900})
    SCREENSHOTS.mkdir(parents=True, exist_ok=True)
    page.screenshot(path=str(SCREENSHOTS / "overview.png"), full_page=True)

    # Keyboard: a tile's link is reachable and opens the vehicle page.
    page.locator('.tile[data-vehicle="SIM-001"] .tile-link').focus()
    page.keyboard.press("Enter")
    expect(page.locator("#v-title")).to_have_text("SIM-001", timeout=LONG)


def test_vehicle_page_charts_and_history(page: Page, gateway: Gateway) -> None:
    login_by_url(page, gateway, gateway.admin)
    page.locator('.tile[data-vehicle="SIM-003"] .tile-link').click()
    expect(page).to_have_url(re.compile(r"#/vehicle/SIM-003$"))
    panel = page.locator(".unit-panel").first
    expect(panel.locator('[data-field="v24"]')).to_have_text(re.compile(r"^\d+\.\d\d V$"))
    expect(panel.locator(".diag")).to_contain_text("Diagnosis", timeout=LONG)
    # Charts: drawn from history, extended live.
    # Points from the stored history and the live extension: a line needs two. SOC/SOH come
    # every 5 s and only when they change, so a fresh database may hold one so far.
    at_least = {"voltages": 2, "imbalance": 2, "currents": 2, "battery": 1}
    for chart, n in at_least.items():
        expect(page.locator(f'[data-chart="{chart}"]')).to_have_attribute(
            "data-points", re.compile(rf"^([{n}-9]|\d\d+)$"), timeout=LONG
        )
        expect(page.locator(f'[data-chart="{chart}"] canvas')).to_be_visible()
    expect(page.locator("#timeline .lane").first).to_be_visible(timeout=LONG)
    page.get_by_role("button", name="Last day").click()
    expect(page.get_by_role("button", name="Last day")).to_have_attribute("aria-pressed", "true")
    expect(page.locator('[data-chart="voltages"] canvas')).to_be_visible(timeout=LONG)
    with page.expect_download(timeout=LONG) as dl:
        page.get_by_role("button", name="Export CSV").click()
    csv = Path(dl.value.path()).read_text()
    assert csv.startswith("time_utc,ts,v12,v24") and csv.count("\n") > 1, csv[:200]
    for width in (1024, 1920):
        assert_no_horizontal_overflow(page, width)
    page.set_viewport_size({"width": 1280, "height": 900})
    page.get_by_role("button", name="Last hour").click()
    expect(page.locator('[data-chart="voltages"]')).to_have_attribute(
        "data-points", re.compile(r"^([2-9]|\d\d+)$"), timeout=LONG
    )
    # A custom range around the few minutes a fresh database holds, for a readable screenshot.
    now = time.time()
    page.locator("#c-from").fill(time.strftime("%Y-%m-%dT%H:%M", time.localtime(now - 180)))
    page.locator("#c-to").fill(time.strftime("%Y-%m-%dT%H:%M", time.localtime(now + 60)))
    page.get_by_role("button", name="Show").click()
    expect(page.locator('[data-chart="voltages"]')).to_have_attribute(
        "data-points", re.compile(r"^([2-9]|\d\d+)$"), timeout=LONG
    )
    SCREENSHOTS.mkdir(parents=True, exist_ok=True)
    page.screenshot(path=str(SCREENSHOTS / "vehicle.png"), full_page=True)


def test_operator_turns_on_jump_start_override_and_sees_it_confirmed(
    page: Page, gateway: Gateway
) -> None:
    login_by_url(page, gateway, gateway.key("operator"), "#/vehicle/SIM-001")
    controls = page.locator(".controls").first
    row = controls.locator('[data-control="jump_start_override"]')
    expect(row.locator("[data-now]")).to_have_text("off", timeout=LONG)
    row.get_by_role("button", name="Turn on").click()
    dialog = page.locator("#confirm")
    expect(dialog).to_contain_text("jump-start override")
    dialog.get_by_role("button", name="Send").click()
    state = controls.locator(".cmd-state").first
    expect(state).to_have_text(re.compile("queued|sending|confirmed"), timeout=LONG)
    expect(state).to_have_text("confirmed", timeout=LONG)
    expect(row.locator("[data-now]")).to_have_text("on", timeout=LONG)

    # A parameter outside the manuals' range is refused before anything is sent.
    form = controls.locator(".param-form")
    form.get_by_label("Parameter").select_option("fault_timer_s")
    form.get_by_label("Value").fill("9999")
    form.get_by_role("button", name="Write…").click()
    expect(form.locator(".param-hint")).to_contain_text("outside the manuals' range")
    expect(dialog).to_be_hidden()


def test_write_dialogs_list_every_unit_the_broadcast_reaches(page: Page, gateway: Gateway) -> None:
    # SIM-003 has two units on one bus (SA 30 and 31): a write from either panel reaches both.
    login_by_url(page, gateway, gateway.key("operator"), "#/vehicle/SIM-003")
    controls = page.locator('.unit-panel[data-unit="31"] .controls')
    expect(controls).to_be_visible(timeout=LONG)
    dialog = page.locator("#confirm")
    units = dialog.locator("#confirm-units li")
    # A parameter write: listed before anything is sent; cancelled, nothing is.
    form = controls.locator(".param-form")
    form.get_by_label("Parameter").select_option("ov_setpoint_v")
    form.get_by_label("Value").fill("32")
    form.get_by_role("button", name="Write…").click()
    expect(dialog).to_be_visible()
    expect(dialog).to_contain_text("reaches every equalizer on bus SIM-003/sim")
    expect(units).to_have_count(2)
    expect(units.nth(0)).to_have_text(re.compile(r"^SA 30 · 80-series"))
    expect(units.nth(1)).to_have_text(re.compile(r"^SA 31 · 80-series"))
    dialog.get_by_role("button", name="Cancel").click()
    expect(dialog).to_be_hidden()
    expect(controls.locator(".cmd")).to_have_count(0)
    # A control: the same list; sent, it is accepted for both and confirmed by both.
    row = controls.locator('[data-control="jump_start_override"]')
    row.get_by_role("button", name="Turn on").click()
    expect(units).to_have_count(2)
    expect(units.nth(0)).to_have_attribute("data-sa", "30")
    dialog.get_by_role("button", name="Send").click()
    expect(controls.locator(".cmd-state").first).to_have_text("confirmed", timeout=LONG)
    for sa in (30, 31):
        row = page.locator(f'.unit-panel[data-unit="{sa}"] [data-control="jump_start_override"]')
        expect(row.locator("[data-now]")).to_have_text("on", timeout=LONG)
    # A vehicle with one unit: the dialog names that one.
    page.goto(f"{gateway.base}/#/vehicle/SIM-001")
    one = page.locator(".controls").first
    one.locator('[data-control="can_onoff_enable"]').get_by_role("button", name="Turn off").click()
    expect(dialog).to_contain_text("reaches the one equalizer on bus SIM-001/sim")
    expect(units).to_have_count(1)
    expect(units.first).to_have_attribute("data-sa", "30")
    dialog.get_by_role("button", name="Cancel").click()


def test_a_command_sent_but_never_confirmed_shows_unconfirmed(page: Page, gateway: Gateway) -> None:
    """Frames handed to an interface that takes them and delivers them nowhere (a virtual
    channel no unit is on): the command ends `unconfirmed`, shown as such with its reason."""
    bus = "SIM-004/sim"
    commands = gateway.app.state.rt.commands
    real = commands.writers[bus]
    config = BusConfig(name=bus, vehicle_id="SIM-004", interface="virtual",
                       channel=f"nowhere-{time.monotonic_ns()}")  # fmt: skip
    nowhere = BusReader(config)
    asyncio.run_coroutine_threadsafe(nowhere.start(), gateway.loop).result(10)
    gateway.call(commands.writers.__setitem__, bus, BusWriter(nowhere))
    # A shorter default expiry than the gateway's 30 s, so the wait for the end is short.
    expiry = commands.settings.command_expiry_s
    gateway.call(setattr, commands.settings, "command_expiry_s", 6.0)
    try:
        login_by_url(page, gateway, gateway.key("operator"), "#/vehicle/SIM-004")
        controls = page.locator(".controls").first
        row = controls.locator('[data-control="jump_start_override"]')
        expect(row.locator("[data-now]")).to_have_text("off", timeout=LONG)
        row.get_by_role("button", name="Turn on").click()
        page.locator("#confirm").get_by_role("button", name="Send").click()
        state = controls.locator(".cmd-state").first
        expect(state).to_have_text("sending", timeout=LONG)
        # At the expiry it ends, sent and never confirmed.
        expect(state).to_have_text("unconfirmed", timeout=LONG)
        expect(state).to_have_attribute("title", re.compile("may still take effect"))
        reason = controls.locator(".cmd .warn").first
        expect(reason).to_contain_text("not confirmed by the status flags")
        expect(reason).to_contain_text("it may still take effect")
        expect(row.locator("[data-now]")).to_have_text("off")
    finally:
        gateway.call(setattr, commands.settings, "command_expiry_s", expiry)
        gateway.call(commands.writers.__setitem__, bus, real)
        asyncio.run_coroutine_threadsafe(nowhere.stop(), gateway.loop).result(30)


def test_viewer_sees_no_controls_and_the_api_refuses(page: Page, gateway: Gateway) -> None:
    viewer = gateway.key("viewer")
    login_by_url(page, gateway, viewer, "#/vehicle/SIM-001")
    expect(page.locator(".unit-panel").first).to_be_visible(timeout=LONG)
    expect(page.locator('.unit-panel [data-field="v12"]').first).to_be_visible()
    expect(page.locator(".controls")).to_have_count(0)
    expect(page.get_by_role("button", name="Turn on")).to_have_count(0)
    r = web.post(
        f"{gateway.base}/api/v1/vehicles/SIM-001/commands",
        json={"jump_start_override": True},
        headers={"Authorization": f"Bearer {viewer}"},
    )
    assert r.status_code == 403


def test_websocket_dropped_and_restored(page: Page, gateway: Gateway) -> None:
    routes: list[Any] = []
    blocked = {"on": False}

    def handle(ws: Any) -> None:
        if blocked["on"]:
            ws.close(code=4000, reason="dropped by the test")
            return
        ws.connect_to_server()
        routes.append(ws)

    page.route_web_socket(re.compile(r".*/api/v1/ws.*"), handle)
    login_by_url(page, gateway, gateway.admin)
    assert routes, "the dashboard did not open its websocket"
    blocked["on"] = True
    for ws in routes:
        ws.close(code=4000, reason="dropped by the test")
    banner = page.locator("#conn-banner")
    expect(banner).to_be_visible(timeout=LONG)
    expect(banner).to_contain_text("Live connection lost")
    expect(page.locator("#conn")).to_have_attribute("data-state", re.compile("lost|connecting"))
    blocked["on"] = False
    # Reconnects by itself (backoff); the banner goes and live values flow again.
    expect(page.locator("#conn")).to_have_attribute("data-state", "live", timeout=LONG)
    expect(banner).to_be_hidden()
    assert len(routes) >= 2


def test_alerts_on_tiles_acknowledged_live_and_history(page: Page, gateway: Gateway) -> None:
    login_by_url(page, gateway, gateway.key("operator"))
    gateway.call(gateway.sim.fail_equalizer, "SIM-004")
    # The alert reaches the vehicle's tile live (the unit's fault timer is 10 s).
    chip = page.locator('.tile[data-vehicle="SIM-004"] .alert-chip[data-rule="equalizer_fault"]')
    expect(chip).to_be_visible(timeout=LONG)
    expect(chip).to_have_attribute("data-severity", "critical")
    page.get_by_role("link", name="Alerts").click()
    expect(page).to_have_url(re.compile(r"#/alerts$"))
    row = page.locator('#open-table tr[data-vehicle="SIM-004"][data-rule="equalizer_fault"]')
    expect(row).to_have_attribute("data-state", "active", timeout=LONG)
    expect(row).to_contain_text("EQFLT")
    row.get_by_role("button", name="Acknowledge").click()
    expect(page.locator("#ack-dialog")).to_be_visible()
    page.get_by_label("Comment (optional)").fill("fitter on the way")
    page.locator("#ack-ok").click()
    expect(row).to_have_attribute("data-state", "acknowledged", timeout=LONG)
    expect(row).to_contain_text("operator (browser test)")
    expect(row).to_contain_text("fitter on the way")
    expect(row.get_by_role("button", name="Acknowledge")).to_have_count(0)
    history = page.locator("#history-table")
    expect(history).to_contain_text("fitter on the way", timeout=LONG)
    for width in (1024, 1920):
        assert_no_horizontal_overflow(page, width)
    page.set_viewport_size({"width": 1280, "height": 900})
    SCREENSHOTS.mkdir(parents=True, exist_ok=True)
    page.screenshot(path=str(SCREENSHOTS / "alerts.png"), full_page=True)
    # Repaired: the alert leaves the open list live and the history shows it cleared.
    gateway.call(gateway.sim.restore_equalizer, "SIM-004")
    expect(row).to_have_count(0, timeout=LONG)
    page.get_by_label("State").select_option("cleared")
    expect(history.locator("tr[data-state=cleared]").first).to_be_visible(timeout=LONG)
    expect(history).to_contain_text("SIM-004")
    # A viewer sees the alerts but no Acknowledge button.
    page.get_by_role("button", name="Log out").click()
    login_by_url(page, gateway, gateway.key("viewer"), "#/alerts")
    expect(page.locator("#open-alerts")).to_be_visible(timeout=LONG)
    expect(page.locator("#alert-history table")).to_be_visible(timeout=LONG)
    expect(page.get_by_role("button", name="Acknowledge")).to_have_count(0)


def test_a_parked_vehicle_is_shown_apart_greyed_without_an_alert(
    page: Page, gateway: Gateway
) -> None:
    login_by_url(page, gateway, gateway.admin)
    tiles = page.locator("#tiles")
    expect(tiles.locator('.tile[data-vehicle="SIM-003"]')).to_be_visible(timeout=LONG)
    expect(page.locator("#parked")).to_be_hidden()
    # Ignition off: the whole bus is silent. The tile moves to the parked section, greyed,
    # with the time it was last heard and its zone; no alert, no "needs attention".
    gateway.call(gateway.sim.ignition_off, "SIM-003")
    parked = page.locator('#parked-tiles .tile[data-vehicle="SIM-003"]')
    expect(parked).to_be_visible(timeout=LONG)
    expect(parked).to_have_attribute("data-severity", "parked")
    expect(parked.locator(".state")).to_have_text("Parked")
    expect(parked.locator(".heard")).to_have_text(re.compile(r"^last heard \d\d:\d\d \S+"))
    expect(parked.locator(".diag").first).to_contain_text("Parked")
    expect(parked).not_to_contain_text("needs attention")
    expect(page.locator("#parked-h")).to_contain_text("Parked (1)")
    assert tiles.locator('.tile[data-vehicle="SIM-003"]').count() == 0
    SCREENSHOTS.mkdir(parents=True, exist_ok=True)
    page.screenshot(path=str(SCREENSHOTS / "parked.png"), full_page=True)
    page.get_by_label("Needs attention only").check()
    expect(parked).to_be_hidden()
    page.get_by_label("Needs attention only").uncheck()
    # Ignition on: back among the others, online, and nothing was raised for it.
    gateway.call(gateway.sim.ignition_on, "SIM-003")
    back = tiles.locator('.tile[data-vehicle="SIM-003"]')
    expect(back.locator(".state")).to_have_text("Online", timeout=LONG)
    expect(page.locator("#parked")).to_be_hidden()
    r = web.get(
        f"{gateway.base}/api/v1/alerts?vehicle=SIM-003&limit=100",
        headers={"Authorization": f"Bearer {gateway.admin}"},
    )
    assert r.status_code == 200, r.text
    assert not [a for a in r.json()["alerts"] if a["rule"] in ("offline", "not_reporting")]
