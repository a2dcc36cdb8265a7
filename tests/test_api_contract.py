"""The OpenAPI document as tools read it: valid OpenAPI, every operation named, tagged, summed
up and answered with a schema; `/docs` renders from the gateway's own files with no network."""

from __future__ import annotations

import re
import shutil
from pathlib import Path
from typing import Any

import httpx
import pytest
from openapi_spec_validator import validate

from eqgw.config import Settings
from eqgw.main import create_app
from tests.proc_helpers import Process, eqgw, free_port
from tests.support import web

OPERATION_ID = re.compile(r"^[a-z]+(_[a-z0-9]+)*$")
CHROMIUM = "/usr/bin/chromium"


@pytest.fixture(scope="module")
def document(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    db = tmp_path_factory.mktemp("openapi") / "eqgw.db"
    doc: dict[str, Any] = create_app(Settings(database_url=f"sqlite:///{db}")).openapi()
    return doc


def _operations(doc: dict[str, Any]) -> list[tuple[str, str, dict[str, Any]]]:
    return [
        (method.upper(), path, op)
        for path, methods in doc["paths"].items()
        for method, op in methods.items()
    ]


def test_the_document_is_valid_openapi(document: dict[str, Any]) -> None:
    validate(document)  # raises on any violation of the OpenAPI 3.1 schema


def test_every_operation_is_named_tagged_and_summed_up(document: dict[str, Any]) -> None:
    ops = _operations(document)
    assert len(ops) >= 40
    ids = [op["operationId"] for _, _, op in ops]
    assert len(set(ids)) == len(ids), sorted(i for i in ids if ids.count(i) > 1)
    for method, path, op in ops:
        where = f"{method} {path}"
        assert OPERATION_ID.match(op["operationId"]), where
        assert "api_v1" not in op["operationId"] and not op["operationId"].endswith(
            ("_get", "_post", "_patch", "_delete")
        ), (where, op["operationId"])
        assert op.get("tags"), where
        summary = op.get("summary", "")
        assert summary and "\n" not in summary, where
        # Not a name FastAPI made up from the function ("Get Keys").
        assert summary != op["operationId"].replace("_", " ").title(), (where, summary)
    assert "list_vehicles" in ids and "get_vehicle_live" in ids


def test_a_keys_scope_keeps_its_component_names(document: dict[str, Any]) -> None:
    # Two classes show a key's scope: the request bodies' (eqgw.security.schemas.KeyScope)
    # and the answers' (ScopeOut, named KeyScope in the document). Generated clients name
    # their types after these components.
    names = set(document["components"]["schemas"])
    assert {"KeyScope-Input", "KeyScope-Output"} <= names
    assert not {n for n in names if "ScopeOut" in n or "__" in n}, sorted(names)


def test_every_success_response_publishes_a_schema(document: dict[str, Any]) -> None:
    missing = []
    for method, path, op in _operations(document):
        for code, response in op["responses"].items():
            if not code.startswith("2") or code == "204":
                continue
            content = response.get("content") or {}
            if not content or not all(media.get("schema") for media in content.values()):
                missing.append(f"{method} {path} {code}")
    assert not missing, missing


async def test_docs_use_only_the_gateways_own_files(tmp_path: Path) -> None:
    app = create_app(Settings(database_url=f"sqlite:///{tmp_path / 'eqgw.db'}"))
    transport = httpx.ASGITransport(app=app)  # the page and files need no lifespan
    async with httpx.AsyncClient(transport=transport, base_url="http://gw") as client:
        page = await client.get("/docs")
        assert page.status_code == 200
        urls = re.findall(r"""(?:src|href|url)\s*[=:]\s*['"]([^'"]+)['"]""", page.text)
        assert urls and not [u for u in urls if "//" in u], urls
        for url in urls:
            asset = await client.get(url)
            assert asset.status_code == 200 and asset.content, url
        assert (await client.get("/redoc")).status_code == 404  # ReDoc needs a CDN: not offered


@pytest.mark.browser
def test_docs_render_in_a_browser_with_no_network(tmp_path: Path) -> None:
    if shutil.which(CHROMIUM) is None:
        pytest.skip(f"no chromium at {CHROMIUM}")
    sync_api = pytest.importorskip("playwright.sync_api")
    port = free_port()
    proc = Process(
        eqgw("serve", "--port", str(port)),
        tmp_path,
        {"EQGW_DATABASE_URL": f"sqlite:///{tmp_path / 'eqgw.db'}"},
    )
    base = f"http://127.0.0.1:{port}"
    outside: list[str] = []
    try:
        proc.wait_line(re.compile("serving on"))
        assert web.get(f"{base}/readyz", timeout=10).status_code == 200
        with sync_api.sync_playwright() as p:
            browser = p.chromium.launch(
                executable_path=CHROMIUM, args=["--headless", "--no-sandbox", "--disable-gpu"]
            )
            try:
                page = browser.new_page()

                def only_the_gateway(route: Any) -> None:
                    if route.request.url.startswith(base):
                        route.continue_()
                    else:  # the network beyond the gateway is not there
                        outside.append(route.request.url)
                        route.abort()

                page.route("**/*", only_the_gateway)
                page.goto(f"{base}/docs")
                paths = page.locator(".opblock-summary-path")
                sync_api.expect(paths.first).to_be_visible(timeout=60_000)
                assert "/api/v1/vehicles" in paths.all_inner_texts()
            finally:
                browser.close()
    finally:
        proc.stop()
    assert not outside, outside


async def test_options_and_405_list_exactly_the_methods_of_the_path(tmp_path: Path) -> None:
    """`OPTIONS` on a path answers 204 with `Allow` naming every method the path has (its
    operations in the document, and OPTIONS); it used to be a 405 naming one route's method
    (`/api/v1/keys`: `POST`, not `GET, POST`). A method the path does not have is a 405 with
    the same `Allow`."""
    app = create_app(Settings(database_url=f"sqlite:///{tmp_path / 'eqgw.db'}"))
    doc = app.openapi()
    transport = httpx.ASGITransport(app=app)
    wrong: dict[str, tuple[str | None, str]] = {}
    async with httpx.AsyncClient(transport=transport, base_url="http://test") as client:
        # A path may be of more than one template (/vehicles/import is also /vehicles/{id}).
        patterns = {
            re.compile("^" + re.sub(r"\\\{[^}]+\\\}", "[^/]+", re.escape(t)) + "$"): ops
            for t, ops in doc["paths"].items()
        }
        for template in doc["paths"]:
            path = re.sub(r"\{[^}]+\}", "1", template)
            methods = {m.upper() for p, ops in patterns.items() if p.match(path) for m in ops}
            want = ", ".join(sorted(methods | {"OPTIONS"}))
            r = await client.options(path)
            if r.status_code != 204 or r.headers.get("allow") != want or r.content:
                wrong[f"OPTIONS {path}"] = (r.headers.get("allow"), f"{r.status_code} {want}")
            r = await client.put(path)
            if "PUT" not in want and (r.status_code, r.headers.get("allow")) != (405, want):
                wrong[f"PUT {path}"] = (r.headers.get("allow"), f"{r.status_code} {want}")
        r = await client.options("/api/v1/no-such-thing")
        assert r.status_code == 404
    assert not wrong, wrong
