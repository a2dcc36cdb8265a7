"""The fleet view at depot scale, in Chromium against the real gateway with 20 simulated
vehicles: search as you type, sort, the summary's jump to a group, the dense rows, live
updates patching the one node that changed, and no value overlapping or cut at each width
from a phone's 390 px to 2560 px, in tiles and rows.

Fixtures and the login come from tests/test_dashboard.py; every wait is Playwright's `expect`.
"""

from __future__ import annotations

import itertools
import re
import time
from collections.abc import Iterator
from typing import Any

import pytest

from tests.support import web
from tests.test_dashboard import (
    LONG,
    Gateway,
    Page,
    browser,  # noqa: F401  (a fixture)
    expect,
    login_by_url,
    page,  # noqa: F401  (a fixture)
    run_gateway,
)

pytestmark = pytest.mark.browser

FLEET = 20
WIDTHS = (390, 768, 1024, 1366, 1920, 2560)


@pytest.fixture(scope="module")
def fleet(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Gateway]:
    with run_gateway(tmp_path_factory, FLEET) as gw:
        yield gw


def shown_ids(pg: Page, box: str = "#tiles") -> list[str]:
    ids: list[str] = pg.eval_on_selector_all(
        f"{box} > [data-vehicle]", "els => els.map(e => e.dataset.vehicle)"
    )
    return ids


def test_search_sort_jump_and_rows(page: Page, fleet: Gateway) -> None:  # noqa: F811
    page.add_init_script("localStorage.removeItem('eqgw.overview.filters')")
    login_by_url(page, fleet, fleet.admin)
    tiles = page.locator("#tiles > .tile")
    expect(tiles).to_have_count(FLEET, timeout=LONG)
    expect(page.locator('#summary [data-group=""] [data-count]')).to_have_text(str(FLEET))

    # Search filters as you type: id, name or depot, any case.
    box = page.get_by_label("Search")
    box.press_sequentially("sim-01")
    expect(tiles).to_have_count(10)
    assert sorted(shown_ids(page)) == [f"SIM-{n:03d}" for n in range(10, 20)]
    box.fill("SIM-007")
    expect(tiles).to_have_count(1)
    expect(page.locator("#f-count")).to_have_text(f"1 of {FLEET} vehicles")
    box.fill("")
    expect(tiles).to_have_count(FLEET)

    # Sort by id: exactly in order; by lowest voltage: ascending (values stream, so within
    # a few hundredths between the order and the reading).
    page.get_by_label("Sort").select_option("id")
    assert shown_ids(page) == [f"SIM-{n:03d}" for n in range(1, FLEET + 1)]
    page.get_by_label("Sort").select_option("voltage")
    # The tiles near the viewport show their values (the first ones of the order); a tile far
    # from it shows none (its values are dropped until it comes near). A tile's key is its
    # lowest unit's V12.
    v12 = page.eval_on_selector_all(
        "#tiles > .tile",
        "els => els.map(e => [...e.querySelectorAll('[data-field=v12]')]"
        ".map(d => parseFloat(d.textContent)).filter(x => !Number.isNaN(x)))"
        ".filter(xs => xs.length).map(xs => Math.min(...xs))",
    )
    assert len(v12) >= 6, v12
    assert all(a <= b + 0.05 for a, b in itertools.pairwise(v12)), v12

    # A battery fails on one vehicle: sorted by imbalance it comes first, live.
    page.get_by_label("Sort").select_option("imbalance")
    fleet.call(fleet.sim.fail_battery_b, "SIM-013")
    expect(tiles.first).to_have_attribute("data-vehicle", "SIM-013", timeout=LONG)
    # A keyboard user's focus stays on a vehicle the order moves.
    tiles.first.locator(".tile-link").focus()
    page.evaluate(
        "() => { const s = document.querySelector('#f-sort'); s.value = 'id';"
        " s.dispatchEvent(new Event('change', { bubbles: true })); }"
    )
    assert shown_ids(page).index("SIM-013") == 12
    focused = "document.activeElement.closest('[data-vehicle]')?.dataset.vehicle"
    assert page.evaluate(focused) == "SIM-013"
    page.get_by_label("Sort").select_option("imbalance")

    # The summary: a fault makes a critical vehicle; its count jumps to that group alone.
    page.get_by_label("Sort").select_option("worst")
    fleet.call(fleet.sim.fail_equalizer, "SIM-005")
    critical = page.locator('#summary [data-group="critical"]')
    expect(critical.locator("[data-count]")).not_to_have_text("0", timeout=LONG)
    critical.click()
    expect(critical).to_have_attribute("aria-pressed", "true")
    expect(page.locator('#tiles > .tile[data-vehicle="SIM-005"]')).to_be_visible(timeout=LONG)
    groups = page.eval_on_selector_all("#tiles > .tile", "els => els.map(e => e.dataset.group)")
    assert groups and set(groups) == {"critical"}, groups
    n = int(critical.locator("[data-count]").inner_text())
    assert len(groups) == n
    critical.click()
    expect(tiles).to_have_count(FLEET)

    # Live values patch the node in place: the same element, its text changed.
    page.evaluate(
        "() => { window.__tiles = [...document.querySelectorAll('#tiles > .tile')]"
        ".filter(t => t.querySelector('[data-field=v12]'));"
        " window.__texts = window.__tiles.map(t => t.querySelector('[data-field=v12]')"
        ".textContent); }"
    )
    page.wait_for_function(
        "() => window.__tiles.some((t, i) =>"
        " t.querySelector('[data-field=v12]')?.textContent !== window.__texts[i])",
        timeout=LONG,
    )
    assert page.evaluate("window.__tiles.every(t => document.contains(t))")

    # The dense view: a row per vehicle with its numbers; keyboard opens a vehicle.
    page.get_by_role("button", name="Rows").click()
    rows = page.locator("#tiles > .vrow")
    expect(rows).to_have_count(FLEET)
    row = page.locator('#tiles > .vrow[data-vehicle="SIM-009"]')
    expect(row.locator('[data-field="v12"]')).to_have_text(re.compile(r"^\d+\.\d\d V$"))
    expect(row.locator('[data-field="imbalance"]')).to_have_text(re.compile(r"^[+-]?\d+\.\d\d V$"))
    expect(row.locator(".heard")).to_have_text(re.compile(r"\d\d:\d\d"))
    page.get_by_label("Search").fill("SIM-009")
    expect(rows).to_have_count(1)
    row.locator(".row-link").focus()
    page.keyboard.press("Enter")
    expect(page.locator("#v-title")).to_have_text("SIM-009", timeout=LONG)
    fleet.call(fleet.sim.restore_equalizer, "SIM-005")
    fleet.call(fleet.sim.restore_battery_b, "SIM-013")


def test_values_are_drawn_near_the_viewport_heads_everywhere(browser: Any, fleet: Gateway) -> None:  # noqa: F811
    """Every vehicle has its node (name, state, link: search, sort, counts and Tab cover them
    all); its values are drawn only near the viewport: a vehicle far down has none until it
    is scrolled to, and one scrolled far away drops them. A search or sort shows the values
    of what it brings into view at once, not a frame later; the keyboard reaches a vehicle
    whose values are not drawn."""
    context = browser.new_context(viewport={"width": 1280, "height": 400})
    pg = context.new_page()
    pg.add_init_script(
        "localStorage.setItem('eqgw.overview.filters', JSON.stringify({sort: 'id'}))"
    )
    try:
        login_by_url(pg, fleet, fleet.admin)
        tiles = pg.locator("#tiles > .tile")
        expect(tiles).to_have_count(FLEET, timeout=LONG)
        first, last = tiles.first, pg.locator('.tile[data-vehicle="SIM-020"]')
        expect(first.locator('[data-field="v12"]')).to_have_text(re.compile(r"\d V$"))
        expect(last.locator(".tile-link h2")).to_have_text("SIM-020")
        expect(last.locator(".unit")).to_have_count(0)
        last.scroll_into_view_if_needed()
        expect(last.locator('[data-field="v12"]')).to_have_text(re.compile(r"\d V$"))
        expect(first.locator(".unit")).to_have_count(0)  # far above now
        # A search answers with the values of what it shows, drawn before the next frame.
        pg.evaluate("window.scrollTo(0, 0)")
        expect(last.locator(".unit")).to_have_count(0)
        drawn = pg.evaluate(
            """() => {
              const q = document.querySelector('#f-q');
              q.value = 'SIM-020';
              q.dispatchEvent(new Event('input', { bubbles: true }));
              return !!document.querySelector('.tile[data-vehicle="SIM-020"] [data-field=v12]');
            }"""
        )
        assert drawn, "the search showed SIM-020 without its values"
        pg.get_by_label("Search").fill("")
        expect(tiles).to_have_count(FLEET)
        expect(last.locator(".unit")).to_have_count(0, timeout=LONG)
        # A vehicle a filter took out keeps its values while out; put back far from the
        # viewport, it drops them.
        last.scroll_into_view_if_needed()
        expect(last.locator(".unit")).not_to_have_count(0)
        pg.get_by_label("Search").fill("SIM-00")
        expect(tiles).to_have_count(9)
        pg.evaluate("window.scrollTo(0, 0)")
        pg.get_by_label("Search").fill("")
        expect(tiles).to_have_count(FLEET)
        assert pg.evaluate("scrollY") == 0
        expect(last.locator(".unit")).to_have_count(0)
        # The keyboard: a vehicle whose values are not drawn is a Tab stop like any other.
        last.locator(".tile-link").focus()
        pg.keyboard.press("Enter")
        expect(pg.locator("#v-title")).to_have_text("SIM-020", timeout=LONG)
    finally:
        context.close()


# Every value element of every tile or row in the viewport: no two of one vehicle intersect,
# none is cut (its text wider than its box), none leaves its vehicle's box, and the page has
# no sideways scroll. Returns the problems and the vehicles looked at.
# Measured two frames after the last scroll or change: a row just scrolled into view is
# still skipped (`content-visibility: auto`) until the next frame, and positions read from it
# before then came from a layout with its grid rows sized from before its values were drawn
# (items 68 px tall on rows 45 px apart); a frame later the same row measured right.
OVERLAP_JS = """
async (sel) => {
  await new Promise((done) => requestAnimationFrame(() => requestAnimationFrame(done)));
  const bad = [];
  const seen = [];
  const doc = document.documentElement;
  if (doc.scrollWidth > doc.clientWidth) bad.push(`page scrolls sideways: ${doc.scrollWidth} > ${doc.clientWidth}`);
  for (const box of document.querySelectorAll(sel.box)) {
    const outer = box.getBoundingClientRect();
    if (outer.bottom <= 0 || outer.top >= innerHeight) continue;
    seen.push(box.dataset.vehicle);
    const els = [...box.querySelectorAll(sel.values)].filter((e) => e.getClientRects().length);
    const rects = els.map((e) => e.getBoundingClientRect());
    els.forEach((e, i) => {
      const r = rects[i];
      if (e.scrollWidth > e.clientWidth + 1 && getComputedStyle(e).display !== "inline")
        bad.push(`${box.dataset.vehicle} ${e.dataset.k || e.className}: cut (${e.scrollWidth} > ${e.clientWidth}) "${e.textContent}"`);
      if (r.left < outer.left - 1 || r.right > outer.right + 1)
        bad.push(`${box.dataset.vehicle} ${e.dataset.k || e.className}: outside its box`);
      for (let j = i + 1; j < els.length; j++) {
        const q = rects[j];
        if (els[i].contains(els[j]) || els[j].contains(els[i])) continue;
        const w = Math.min(r.right, q.right) - Math.max(r.left, q.left);
        const h = Math.min(r.bottom, q.bottom) - Math.max(r.top, q.top);
        if (w > 1 && h > 1)
          bad.push(`${box.dataset.vehicle}: "${els[i].textContent}" overlaps "${els[j].textContent}"`);
      }
    });
  }
  return { bad, seen };
}
"""  # noqa: E501
# Every vehicle in the viewport has its values drawn (they are drawn near the viewport only).
DRAWN_IN_VIEW = """
(box) => [...document.querySelectorAll(box)].every((b) => {
  const r = b.getBoundingClientRect();
  return r.bottom <= 0 || r.top >= innerHeight || b.querySelector(".alert-chips");
})
"""
VIEWS: dict[str, dict[str, str]] = {
    "tiles": {
        "box": "#tiles > .tile",
        "values": "dl.big dd, dl.big dt, .batt b, .tile-link h2, .tile-link .state, .tile-sub",
    },
    "rows": {
        "box": "#tiles > .vrow",
        "values": "[role=cell], .l, .state, .row-link, .c-depot",
    },
}


def overlaps_scrolling_through(pg: Page, sel: dict[str, str]) -> tuple[list[str], set[str]]:
    """OVERLAP_JS a screen at a time from the top of the page to its bottom."""
    bad: list[str] = []
    seen: set[str] = set()
    pg.evaluate("window.scrollTo(0, 0)")
    while True:
        pg.wait_for_function(DRAWN_IN_VIEW, arg=sel["box"], timeout=LONG)
        found = pg.evaluate(OVERLAP_JS, sel)
        bad += found["bad"]
        seen |= set(found["seen"])
        if pg.evaluate("scrollY + innerHeight >= document.documentElement.scrollHeight - 1"):
            return bad, seen
        pg.evaluate("window.scrollBy(0, innerHeight - 50)")


def test_no_value_overlaps_or_is_cut_at_any_width(page: Page, fleet: Gateway) -> None:  # noqa: F811
    page.add_init_script("localStorage.removeItem('eqgw.overview.filters')")
    login_by_url(page, fleet, fleet.admin)
    expect(page.locator("#tiles > .tile")).to_have_count(FLEET, timeout=LONG)
    expect(page.locator('#tiles [data-field="v12"]').first).to_have_text(re.compile(r"\d V$"))
    # Faults with their counts and an alert chip, on a vehicle of two units.
    fleet.call(fleet.sim.fail_equalizer, "SIM-003")
    expect(
        page.locator('.tile[data-vehicle="SIM-003"] .fault[data-fault="EQFLT"]').first
    ).to_be_visible(timeout=LONG)
    problems: dict[str, Any] = {}
    for view, sel in VIEWS.items():
        page.get_by_role("button", name=view.capitalize()).click()
        expect(page.locator(sel["box"])).to_have_count(FLEET)
        for width in WIDTHS:
            page.set_viewport_size({"width": width, "height": 900})
            bad, seen = overlaps_scrolling_through(page, sel)
            if bad:
                problems[f"{view} at {width} px"] = bad[:5]
            assert len(seen) == FLEET, f"{view} at {width} px: looked at {sorted(seen)}"
    fleet.call(fleet.sim.restore_equalizer, "SIM-003")
    assert not problems, problems


def test_vehicle_page_alert_acknowledged_faults_and_parked_since(
    page: Page,  # noqa: F811
    fleet: Gateway,
) -> None:
    """A manager follows a vehicle needing attention: its open alert is on its page, with an
    Acknowledge button that works there; its faults with occurrence counts; a parked vehicle
    says since when."""
    login_by_url(page, fleet, fleet.key("operator"), "#/vehicle/SIM-011")
    fleet.call(fleet.sim.fail_equalizer, "SIM-011")
    card = page.locator('#v-alert-list .alert-card[data-rule="equalizer_fault"]')
    expect(card).to_have_attribute("data-state", "active", timeout=LONG)
    expect(card).to_have_attribute("data-severity", "critical")
    expect(card.locator(".ac-head")).to_contain_text(re.compile(r"raised \d\d:\d\d \S+"))
    card.get_by_role("button", name="Acknowledge").click()
    expect(page.locator("#ack-dialog")).to_be_visible()
    page.get_by_label("Comment (optional)").fill("battery ordered")
    page.locator("#ack-ok").click()
    expect(card).to_have_attribute("data-state", "acknowledged", timeout=LONG)
    expect(card).to_contain_text("battery ordered")
    expect(card.get_by_role("button", name="Acknowledge")).to_have_count(0)
    # The fault, live with its occurrence count, and in the history with its count.
    expect(page.locator('.unit-panel .fault[data-fault="EQFLT"]')).to_contain_text(
        "×", timeout=LONG
    )
    expect(page.locator('#fault-table tr[data-fault="EQFLT"]')).to_be_visible(timeout=LONG)
    fleet.call(fleet.sim.restore_equalizer, "SIM-011")

    # Ignition off: the vehicle page says parked since when, with the zone.
    page.goto(f"{fleet.base}/#/vehicle/SIM-012")
    fleet.call(fleet.sim.ignition_off, "SIM-012")
    expect(page.locator("#v-sub .state")).to_have_text("Parked", timeout=LONG)
    expect(page.locator("#v-sub .since")).to_have_text(re.compile(r"^since \d\d:\d\d \S+"))
    fleet.call(fleet.sim.ignition_on, "SIM-012")
    expect(page.locator("#v-sub .state")).to_have_text("Online", timeout=LONG)


def test_phone_layout_fleet_as_list_alerts_as_cards(browser: Any, fleet: Gateway) -> None:  # noqa: F811
    """At 390 px: the fleet is a list (a card per vehicle), the alerts are cards with "What"
    and Acknowledge in view, and no page scrolls sideways."""
    context = browser.new_context(viewport={"width": 390, "height": 844}, is_mobile=True)
    pg = context.new_page()
    errors: list[str] = []
    pg.on("pageerror", lambda exc: errors.append(str(exc)))
    try:
        login_by_url(pg, fleet, fleet.key("operator"))
        expect(pg.locator("#tiles > .vrow")).to_have_count(FLEET, timeout=LONG)
        fleet.call(fleet.sim.fail_equalizer, "SIM-016")
        sideways = "document.documentElement.scrollWidth > document.documentElement.clientWidth"
        assert not pg.evaluate(sideways)
        pg.goto(f"{fleet.base}/#/alerts")
        row = pg.locator('#open-table tr[data-vehicle="SIM-016"][data-rule="equalizer_fault"]')
        expect(row).to_be_visible(timeout=LONG)
        expect(row.locator('td[data-label="Raised"]')).to_have_text(re.compile(r"^\d\d:\d\d \S+$"))
        what = row.locator('td[data-label="What"]')
        button = row.get_by_role("button", name="Acknowledge")
        for el in (what, button):
            box = el.bounding_box()
            assert box is not None and box["x"] >= 0 and box["x"] + box["width"] <= 390, box
        assert not pg.evaluate(sideways)
        # No element of the alerts page scrolls sideways inside itself either.
        inner = pg.evaluate(
            "[...document.querySelectorAll('#main *')].filter(e => e.scrollWidth > "
            "e.clientWidth + 1 && ['auto', 'scroll'].includes(getComputedStyle(e).overflowX))"
            ".map(e => e.className || e.tagName)"
        )
        assert not inner, inner
        pg.goto(f"{fleet.base}/#/vehicle/SIM-016")
        expect(pg.locator("#v-alert-list .alert-card").first).to_be_visible(timeout=LONG)
        assert not pg.evaluate(sideways)
        fleet.call(fleet.sim.restore_equalizer, "SIM-016")
    finally:
        context.close()
    assert not errors, errors


# Layout shifts of the page from its first paint (not after the user's input), and what moved.
SHIFTS = """
window.__shifts = [];
new PerformanceObserver((list) => {
  for (const e of list.getEntries()) {
    if (e.hadRecentInput) continue;
    const what = e.sources.map((s) => s.node?.id || s.node?.className || s.node?.nodeName);
    window.__shifts.push({ value: e.value, at: Math.round(e.startTime), what: what.join(", ") });
  }
}).observe({ type: "layout-shift", buffered: true });
"""
# Every chart drawn from its history, the status timeline and the fault history loaded.
VEHICLE_LOADED = """
() => [...document.querySelectorAll('[data-chart]')].every((c) => c.dataset.points)
  && document.querySelector('#timeline .lane, #timeline p:not(.muted)')
  && !document.querySelector('#fault-table .muted')
"""


def open_alert(gw: Gateway, vehicle: str, rule: str) -> bool:
    r = web.get(
        f"{gw.base}/api/v1/alerts",
        params={"vehicle": vehicle, "state": "open"},
        headers={"Authorization": f"Bearer {gw.admin}"},
    )
    assert r.status_code == 200, r.text
    return any(a["rule"] == rule for a in r.json()["alerts"])


def test_layout_shift_under_a_tenth_on_every_page(browser: Any, fleet: Gateway) -> None:  # noqa: F811
    """Each page loaded afresh (as from a bookmark) and watched while values stream: its
    cumulative layout shift stays under 0.1 (the overview, a vehicle page with an open alert,
    charts, timeline and fault history, the alerts page)."""
    context = browser.new_context(viewport={"width": 1366, "height": 900})
    fleet.call(fleet.sim.fail_equalizer, "SIM-007")
    try:
        # The alert raised before the pages load: a vehicle turning critical while a page
        # is open moves it (worst first) and its tile, which is the page doing its job.
        login_by_url(context.new_page(), fleet, fleet.admin)
        deadline = time.monotonic() + LONG / 1000
        while not open_alert(fleet, "SIM-007", "equalizer_fault"):
            assert time.monotonic() < deadline, "no equalizer_fault alert was raised"
            time.sleep(0.5)
        pages = {
            "overview": ("/", "#tiles > .tile .alert-chips"),
            "vehicle": ("/#/vehicle/SIM-007", "#v-alert-list .alert-card"),
            "alerts": ("/#/alerts", '#open-table tr[data-vehicle="SIM-007"]'),
        }
        shifts = {}
        for name, (path, ready) in pages.items():
            pg = context.new_page()  # logged in: the context holds the session cookie
            pg.add_init_script(SHIFTS)
            pg.goto(fleet.base + path)
            expect(pg.locator("#conn")).to_have_attribute("data-state", "live", timeout=LONG)
            expect(pg.locator(ready).first).to_be_visible(timeout=LONG)
            if name == "vehicle":
                pg.wait_for_function(VEHICLE_LOADED, timeout=LONG)
            # A little more of the stream: live values, the websocket's snapshots.
            pg.wait_for_timeout(1000)
            shifts[name] = pg.evaluate("window.__shifts")
            pg.close()
        total = {name: sum(s["value"] for s in found) for name, found in shifts.items()}
        assert all(v < 0.1 for v in total.values()), (total, shifts)
    finally:
        fleet.call(fleet.sim.restore_equalizer, "SIM-007")
        context.close()
