"""The OpenAPI document and its browser UI.

Every operation gets an operationId a generated client can use as a method name
(`list_vehicles`, not `list_vehicles_api_v1_vehicles_get`) and a one-line summary. `/docs` is
Swagger UI served from the gateway's own files (static/vendor/swagger-ui, a pinned copy), so it
renders on a network without internet access.
"""

from __future__ import annotations

from typing import Any

from fastapi import FastAPI
from fastapi.openapi.docs import get_swagger_ui_html
from fastapi.responses import HTMLResponse
from fastapi.routing import APIRoute

SWAGGER_UI = "/static/vendor/swagger-ui"

# Route function -> (operationId, summary used when the route has none). A route missing here
# keeps its function's name as operationId; tests/test_api_contract.py checks every operation
# has a unique, meaningful one.
OPERATIONS: dict[str, tuple[str, str]] = {
    "healthz": ("healthz", ""),
    "readyz": ("readyz", ""),
    "metrics": ("metrics", ""),
    "list_vehicles": ("list_vehicles", ""),
    "vehicle_live": ("get_vehicle_live", ""),
    "vehicle_history": ("get_vehicle_history", ""),
    "vehicle_status_history": ("get_vehicle_status", ""),
    "vehicle_faults": ("list_vehicle_faults", ""),
    "fleet_faults": ("list_faults", ""),
    "post_control": ("send_control", ""),
    "post_parameters": ("write_parameters", ""),
    "post_request": ("request_message", ""),
    "get_command": ("get_command", ""),
    "cancel_command": ("cancel_command", ""),
    "list_commands": ("list_commands", ""),
    "get_keys": ("list_keys", "Every API key (never the keys themselves)"),
    "post_key": ("create_key", "Create an API key; the key is in this answer only"),
    "delete_key": ("revoke_key", "Revoke an API key at once"),
    "login": ("log_in", "Log in: exchange an API key for a session cookie"),
    "current": ("get_session", "The session of the cookie and its CSRF token"),
    "logout": ("log_out", "Log out: end the session on the server"),
    "post_rotate": ("rotate_key", "Replace an API key; the old one keeps working for an overlap"),
    "get_audit": ("list_audit", ""),
    "get_rules": ("list_alert_rules", "Every alert rule, built-in and custom"),
    "get_rule": ("get_alert_rule", "One alert rule"),
    "post_rule": ("create_alert_rule", "Create a custom alert rule"),
    "patch_rule": ("update_alert_rule", "Change an alert rule (thresholds, severity, enabled)"),
    "delete_rule": ("delete_alert_rule", "Delete a custom alert rule"),
    "get_mutes": ("list_alert_mutes", "Active and scheduled alert mutes"),
    "post_mute": ("create_alert_mute", "Mute alerts of a vehicle or rule for a while"),
    "delete_mute": ("delete_alert_mute", "End an alert mute"),
    "get_alerts": ("list_alerts", "Alerts, open or all, newest first"),
    "get_alert": ("get_alert", "One alert with its history"),
    "acknowledge": ("acknowledge_alert", "Acknowledge an alert"),
    "me": ("get_me", ""),
    "parameters": ("list_parameters", ""),
    "post_frames": ("ingest_frames", ""),
    "get_webhooks": ("list_webhooks", "Every webhook (secrets never shown)"),
    "post_webhook": ("create_webhook", "Register a webhook; its secret is in this answer only"),
    "get_webhook": ("get_webhook", "One webhook"),
    "patch_webhook": ("update_webhook", "Change a webhook (URL, events, enabled)"),
    "delete_webhook": ("delete_webhook", "Delete a webhook"),
    "post_webhook_test": ("test_webhook", "Send a signed test delivery to a webhook now"),
    "get_deliveries": ("list_webhook_deliveries", "A webhook's delivery log, newest first"),
    "export_faults": ("export_faults", ""),
    "export_alerts": ("export_alerts", ""),
    "export_audit": ("export_audit", ""),
    "export_vehicle_history": ("export_vehicle_history", ""),
    "vehicle_raw": ("export_vehicle_raw", ""),
    "create_vehicle": ("create_vehicle", ""),
    "get_vehicle_config": ("get_vehicle_config", ""),
    "update_vehicle": ("update_vehicle", ""),
    "delete_vehicle": ("delete_vehicle", ""),
    "import_vehicles": ("import_vehicles", ""),
}


def operation_id(route: APIRoute) -> str:
    """The operationId of a route (FastAPI's `generate_unique_id_function`)."""
    return OPERATIONS.get(route.name, (route.name, ""))[0]


def _summaries(doc: dict[str, Any]) -> None:
    """Replace the summaries FastAPI made up from a function name ("Get Keys")."""
    by_id = {op_id: (name, summary) for name, (op_id, summary) in OPERATIONS.items()}
    for methods in doc.get("paths", {}).values():
        for op in methods.values():
            name, summary = by_id.get(op.get("operationId", ""), ("", ""))
            if summary and op.get("summary") == name.replace("_", " ").title():
                op["summary"] = summary


def install_docs(app: FastAPI) -> None:
    """`/docs`: Swagger UI from the gateway's own files; the document's summaries."""
    generate = app.openapi

    def openapi() -> dict[str, Any]:
        if app.openapi_schema is None:
            doc = generate()
            _summaries(doc)
            app.openapi_schema = doc
        return app.openapi_schema

    app.openapi = openapi  # type: ignore[method-assign]

    @app.get("/docs", include_in_schema=False)
    async def swagger_ui() -> HTMLResponse:
        return get_swagger_ui_html(
            openapi_url=app.openapi_url or "/openapi.json",
            title=f"{app.title} API",
            swagger_js_url=f"{SWAGGER_UI}/swagger-ui-bundle.js",
            swagger_css_url=f"{SWAGGER_UI}/swagger-ui.css",
            swagger_favicon_url=f"{SWAGGER_UI}/favicon-32x32.png",
        )
