"""The fleet overview in Chromium while values stream, beside a blank page in the same run.

    python -m bench.dashboard [--vehicles 200 500] [--seconds 20] [--screenshots]

For each fleet size: `eqgw serve --simulate N` in-process (uvicorn in a thread, SQLite in a
temporary folder), Debian's chromium at 1920x1080 driven by Playwright. Prints, for a blank
page and for the overview in tiles and in rows: frames per second (requestAnimationFrame)
and their ratio to the blank page's, long tasks (over 50 ms) and the longest, the share of
the time in long tasks, what the long animation frames spent their time on (scripts by
function, rendering), how long a filter (search typed, narrowing and widening) and a sort take
until the frame after them is drawn (median and worst of ten filters and eight sorts) and the
main thread's CPU time for it, and the page's DOM element count. Then, traced over as long
again, the main thread's CPU share and its tasks over 50 ms by the clock and by CPU time (on a
shared machine a task can take 50 ms by the clock with a few ms of CPU).
`--screenshots` writes docs/screenshots/fleet-N*.png.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import shutil
import socket
import sys
import tempfile
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from statistics import median
from typing import Any

import httpx
import uvicorn
from playwright.sync_api import sync_playwright

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from eqgw.config import Settings
from eqgw.main import create_app
from eqgw.sim.clock import RealtimeClock
from eqgw.sim.fleet import SimulatedFleet
from eqgw.web.settings import ApiSettings

CHROMIUM = "/usr/bin/chromium"
ARGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
]
SCREENSHOTS = Path(__file__).resolve().parent.parent / "docs" / "screenshots"

# Counts frames and long tasks from now on; `window.__bench()` reads them. Each long animation
# frame (over 50 ms) is attributed: the scripts that ran in it (what invoked them, which
# function of which file) and its style and layout time.
PROBE = """
() => {
  const s = { frames: 0, long: 0, longMs: 0, maxMs: 0, t0: performance.now(), by: {} };
  const add = (what, ms) => { s.by[what] = (s.by[what] || 0) + ms; };
  new PerformanceObserver((list) => {
    for (const e of list.getEntries()) {
      s.long += 1; s.longMs += e.duration; s.maxMs = Math.max(s.maxMs, e.duration);
    }
  }).observe({ type: "longtask" });
  new PerformanceObserver((list) => {
    for (const e of list.getEntries()) {
      if (e.duration <= 50) continue;
      for (const sc of e.scripts) {
        const file = (sc.sourceURL || "").split("/").pop();
        add(`${sc.invoker} ${sc.sourceFunctionName || "?"} (${file})`, sc.duration);
      }
      const end = e.startTime + e.duration;
      const render = e.renderStart ? end - e.renderStart : 0;
      if (render) add("rendering (style, layout, paint)", render);
      const scripts = e.scripts.reduce((t, sc) => t + sc.duration, 0);
      const rest = e.duration - render - scripts;
      if (rest > 1) add("other (not in a script or rendering)", rest);
    }
  }).observe({ type: "long-animation-frame" });
  const tick = () => { s.frames += 1; requestAnimationFrame(tick); };
  requestAnimationFrame(tick);
  window.__bench = () => ({ ...s, seconds: (performance.now() - s.t0) / 1000 });
}
"""
# Time from an input event to the frame after it is drawn; marks for the trace around it.
TIMED = """
async ([sel, value, kind, mark]) => {
  const el = document.querySelector(sel);
  performance.mark(`${mark}:start`);
  const t0 = performance.now();
  el.value = value;
  el.dispatchEvent(new Event(kind, { bubbles: true }));
  await new Promise((r) => requestAnimationFrame(() => setTimeout(r, 0)));
  const ms = performance.now() - t0;
  performance.mark(`${mark}:end`);
  return ms;
}
"""


def timed(browser: Any, page: Any, ops: list[tuple[str, str, str]]) -> list[tuple[float, float]]:
    """Each (selector, value, event) dispatched in turn: the time to the frame after it is
    drawn, and the page's main thread CPU time meanwhile (the thread clocks of the marks in a
    trace: unlike the time, it does not grow when other processes hold the cores)."""
    browser.start_tracing(page=page, categories=["blink.user_timing"])
    times = [page.evaluate(TIMED, [sel, v, kind, f"op{i}"]) for i, (sel, v, kind) in enumerate(ops)]
    trace = json.loads(browser.stop_tracing())
    events = trace["traceEvents"] if isinstance(trace, dict) else trace
    tts = {e["name"]: e["tts"] for e in events if e.get("name", "").startswith("op")}
    return [(ms, (tts[f"op{i}:end"] - tts[f"op{i}:start"]) / 1000) for i, ms in enumerate(times)]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port: int = s.getsockname()[1]
        return port


@contextmanager
def gateway(vehicles: int) -> Iterator[tuple[str, str]]:
    """The gateway with a simulated fleet; (base URL, admin key) once every unit is heard."""
    tmp = Path(tempfile.mkdtemp(prefix="eqgw-bench-dash-"))
    first: list[str] = []
    port = _free_port()
    app = create_app(
        Settings(database_url=f"sqlite:///{tmp / 'eqgw.db'}"),
        api=ApiSettings(port=port),
        sim=SimulatedFleet(vehicles, seed=1, clock=RealtimeClock()),
        on_first_key=first.append,
    )
    server = uvicorn.Server(uvicorn.Config(app, host="127.0.0.1", port=port, log_level="warning"))
    loop = asyncio.new_event_loop()
    thread = threading.Thread(target=loop.run_until_complete, args=(server.serve(),), daemon=True)
    thread.start()
    base = f"http://127.0.0.1:{port}"
    deadline = time.monotonic() + 300
    try:
        while not server.started:
            if time.monotonic() > deadline or not thread.is_alive():
                raise SystemExit("the gateway did not start")
            time.sleep(0.1)
        while True:
            r = httpx.get(
                f"{base}/api/v1/vehicles", headers={"Authorization": f"Bearer {first[0]}"}
            )
            units = [u for v in r.json()["vehicles"] for u in v["units"]]
            if len(r.json()["vehicles"]) >= vehicles and units and all(u["v12"] for u in units):
                break
            if time.monotonic() > deadline:
                raise SystemExit("the simulated fleet was not heard within 300 s")
            time.sleep(1)
        yield base, first[0]
    finally:
        server.should_exit = True
        thread.join(timeout=120)
        if not thread.is_alive():
            loop.close()
        shutil.rmtree(tmp, ignore_errors=True)


# Cumulative layout shift (no user input) of each page from its first paint.
CLS = """
window.__cls = 0;
new PerformanceObserver((list) => {
  for (const e of list.getEntries()) if (!e.hadRecentInput) window.__cls += e.value;
}).observe({ type: "layout-shift", buffered: true });
"""


def layout_shift(ctx: Any, base: str, vehicle: str) -> str:
    """Each page opened afresh (a full load, as from a bookmark), its shift after 8 s."""
    out = []
    for name, path in (
        ("overview", "/"),
        ("vehicle", f"/#/vehicle/{vehicle}"),
        ("alerts", "/#/alerts"),
    ):
        page = ctx.new_page()
        page.add_init_script(CLS)
        page.goto(base + path)
        page.wait_for_selector('#conn[data-state="live"]', timeout=120_000)
        time.sleep(8)
        out.append(f"{name} {page.evaluate('window.__cls'):.3f}")
        page.close()
    return "layout shift: " + ", ".join(out)


def measure(page: Any, seconds: float) -> dict[str, Any]:
    page.evaluate(PROBE)
    time.sleep(seconds)
    s: dict[str, Any] = page.evaluate("window.__bench()")
    return {
        "fps": s["frames"] / s["seconds"],
        "long": s["long"],
        "max_ms": s["maxMs"],
        "busy": s["longMs"] / 1000 / s["seconds"],
        "by": s["by"],
    }


def main_thread_tasks(browser: Any, page: Any, seconds: float) -> dict[str, float]:
    """The page's main thread over `seconds` in a trace: its CPU time's share, and its tasks
    over 50 ms by the clock and by CPU time (a task the clock finds long but that used
    little CPU waited for a core that other processes held)."""
    browser.start_tracing(page=page, categories=["disabled-by-default-devtools.timeline"])
    time.sleep(seconds)
    trace = json.loads(browser.stop_tracing())
    events = trace["traceEvents"] if isinstance(trace, dict) else trace
    mains = {
        (e["pid"], e["tid"])
        for e in events
        if e.get("ph") == "M" and e.get("args", {}).get("name") == "CrRendererMain"
    }
    by_thread: dict[tuple[int, int], list[dict[str, Any]]] = {t: [] for t in mains}
    for e in events:
        key = (e.get("pid"), e.get("tid"))
        if e.get("name") == "RunTask" and e.get("ph") == "X" and key in by_thread:
            by_thread[key].append(e)
    # The page's renderer: the main thread that worked most.
    tasks = max(by_thread.values(), key=lambda ts: sum(t.get("tdur", 0) for t in ts), default=[])
    cpu = [t.get("tdur", 0) / 1000 for t in tasks]
    return {
        "cpu_share": sum(cpu) / 1000 / seconds,
        "long_wall": sum(1 for t in tasks if t["dur"] > 50_000),
        "long_cpu": sum(1 for c in cpu if c > 50),
        "max_cpu": max(cpu, default=0.0),
    }


def summary(ops: list[tuple[float, float]]) -> str:
    """Median and worst time of the operations, and their median main-thread CPU time."""
    ms = [t for t, _ in ops]
    cpu = median(c for _, c in ops)
    return f"{median(ms):.0f} ms (worst {max(ms):.0f}, CPU {cpu:.0f} ms)"


def attribution(by: dict[str, float]) -> str:
    """What the long animation frames spent their time on, most first."""
    top = sorted(by.items(), key=lambda kv: -kv[1])[:4]
    return "; ".join(f"{what} {ms:.0f} ms" for what, ms in top) or "none"


def run(vehicles: int, seconds: float, shots: bool) -> list[str]:
    lines: list[str] = []

    def say(line: str) -> None:
        print(line, flush=True)
        lines.append(line)

    with gateway(vehicles) as (base, key), sync_playwright() as p:
        browser = p.chromium.launch(executable_path=CHROMIUM, args=ARGS)
        ctx = browser.new_context(viewport={"width": 1920, "height": 1080})
        page = ctx.new_page()
        page.set_content("<!doctype html><title>blank</title><p>blank</p>")
        blank = measure(page, seconds)
        say(
            f"{vehicles:>4} vehicles  blank page        {blank['fps']:5.1f} fps"
            f"  long tasks {blank['long']:.0f} (max {blank['max_ms']:.0f} ms)"
        )
        page.add_init_script("localStorage.removeItem('eqgw.overview.filters')")
        # Logged in as a person is: the key into the login form (a session cookie).
        page.goto(f"{base}/")
        page.get_by_label("API key").fill(key)
        page.get_by_role("button", name="Log in").click()
        page.wait_for_function(
            "(n) => document.querySelectorAll('#tiles > .tile').length >= n",
            arg=vehicles,
            timeout=300_000,
        )
        page.wait_for_selector('#conn[data-state="live"]', timeout=120_000)
        for view in ("tiles", "rows"):
            if view == "rows":
                page.get_by_role("button", name="Rows").click()
                page.wait_for_function(
                    "(n) => document.querySelectorAll('#tiles > .vrow').length >= n",
                    arg=vehicles,
                )
            time.sleep(2)  # settle after the first render
            m = measure(page, seconds)
            dom = page.evaluate("document.getElementsByTagName('*').length")
            # Each twice over: a search narrowing and widening (back to every vehicle), sorts
            # that move most nodes.
            filt = timed(
                browser,
                page,
                [("#f-q", q, "input") for q in ("SIM-01", "SIM-0", "", "SIM-4", "") * 2],
            )
            sort = timed(
                browser,
                page,
                [("#f-sort", s, "change") for s in ("imbalance", "voltage", "soc", "worst") * 2],
            )
            say(
                f"{vehicles:>4} vehicles  overview ({view:5}) {m['fps']:5.1f} fps"
                f"  ratio {m['fps'] / blank['fps']:.2f}"
                f"  long tasks {m['long']:.0f} in {seconds:.0f} s (max {m['max_ms']:.0f} ms,"
                f" {m['busy'] * 100:.0f} % of the time)"
                f"  filter {summary(filt)}  sort {summary(sort)}  DOM {dom}"
            )
            say(f"{vehicles:>4} vehicles  long frames ({view:5}) spent in: {attribution(m['by'])}")
            t = main_thread_tasks(browser, page, seconds)
            say(
                f"{vehicles:>4} vehicles  main thread ({view:5}) CPU {t['cpu_share'] * 100:.0f} %"
                f" of the time; tasks over 50 ms in {seconds:.0f} s: {t['long_wall']:.0f} by"
                f" the clock, {t['long_cpu']:.0f} in CPU time (longest {t['max_cpu']:.0f} ms CPU)"
            )
            if shots:
                SCREENSHOTS.mkdir(parents=True, exist_ok=True)
                name = f"fleet-{vehicles}{'' if view == 'tiles' else '-rows'}.png"
                page.screenshot(path=str(SCREENSHOTS / name))
        say(f"{vehicles:>4} vehicles  " + layout_shift(ctx, base, "SIM-003"))
        browser.close()
    return lines


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--vehicles", type=int, nargs="+", default=[200, 500])
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--screenshots", action="store_true")
    a = ap.parse_args()
    for n in a.vehicles:
        run(n, a.seconds, a.screenshots)


if __name__ == "__main__":
    main()
