"""`eqgw serve` (ingest + API in one process) and `eqgw keys create|list|revoke`."""

from __future__ import annotations

import argparse
import sys
import time


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """Add `eqgw serve` and `eqgw keys` to the command line."""
    p = subparsers.add_parser(
        "serve",
        help="run migrations, the ingest on the configured buses and the API",
        description="Run the gateway: migrations, ingest, command delivery and the HTTP API.",
    )
    p.add_argument("--config", metavar="FILE", help="TOML fleet file (or EQGW_CONFIG)")
    p.add_argument("--host", help="address to listen on (default EQGW_API_HOST or 127.0.0.1)")
    p.add_argument("--port", type=int, help="port (default EQGW_API_PORT or 8000)")
    p.add_argument(
        "--simulate",
        type=int,
        metavar="N",
        default=0,
        help="add an in-process simulated fleet of N vehicles (no hardware needed)",
    )
    p.add_argument("--seed", type=int, default=0, help="seed of the simulated fleet")
    p.set_defaults(func=serve)

    k = subparsers.add_parser("keys", help="manage API keys")
    k.add_argument("--config", metavar="FILE", help="TOML fleet file (or EQGW_CONFIG)")
    ksub = k.add_subparsers(dest="keys_command", metavar="ACTION")
    c = ksub.add_parser("create", help="create a key and print it (shown once)")
    c.add_argument(
        "--role",
        required=True,
        choices=("viewer", "operator", "admin", "ingest"),
        help="viewer < operator < admin; ingest only posts forwarded frames (eqgw forward)",
    )
    c.add_argument("--name", required=True)
    c.set_defaults(func=keys_create)
    ls = ksub.add_parser("list", help="list keys (never the keys themselves)")
    ls.set_defaults(func=keys_list)
    r = ksub.add_parser("revoke", help="revoke a key by id")
    r.add_argument("id", type=int)
    r.set_defaults(func=keys_revoke)
    k.set_defaults(func=lambda _args: _help(k))


def _help(parser: argparse.ArgumentParser) -> int:
    parser.print_help()
    return 2


def _settings(args: argparse.Namespace) -> object:
    from app.config import ConfigError, load_settings

    try:
        return load_settings(getattr(args, "config", None))
    except ConfigError as exc:
        print(f"eqgw: {exc}", file=sys.stderr)
        raise SystemExit(2) from exc


def serve(args: argparse.Namespace) -> int:
    """Entry point of `eqgw serve`."""
    import uvicorn

    from app.api.settings import ApiSettings
    from app.config import Settings
    from app.main import create_app

    settings = _settings(args)
    assert isinstance(settings, Settings)
    api = ApiSettings()
    updates = {k: v for k, v in (("host", args.host), ("port", args.port)) if v is not None}
    api = api.model_copy(update=updates)
    sim = None
    if args.simulate:
        from app.sim.clock import RealtimeClock
        from app.sim.fleet import SimulatedFleet

        sim = SimulatedFleet(args.simulate, seed=args.seed, clock=RealtimeClock())
    base = api.public_url or f"http://{api.host}:{api.port}"

    def show_first_key(key: str) -> None:
        # Like Jupyter: the only time this key is ever shown.
        print("eqgw: first start, created an admin key (shown once, store it now):", flush=True)
        print(f"    {key}", flush=True)
        print(f"eqgw: open {base}/?key={key}", flush=True)
        print(f"eqgw: API docs at {base}/docs", flush=True)

    app = create_app(settings, api=api, sim=sim, on_first_key=show_first_key)
    print(
        f"eqgw: serving on {base} ({len(app.state.settings.buses)} buses"
        + (f", {args.simulate} simulated vehicles" if args.simulate else "")
        + ")",
        flush=True,
    )
    uvicorn.run(app, host=api.host, port=api.port, log_level="warning", ws="websockets-sansio")
    return 0


def _engine(args: argparse.Namespace):  # type: ignore[no-untyped-def]
    from app.config import Settings
    from app.store.engine import create_engine
    from app.store.migrate import upgrade_engine

    settings = _settings(args)
    assert isinstance(settings, Settings)
    engine = create_engine(settings.database_url)
    upgrade_engine(engine)
    return engine


def keys_create(args: argparse.Namespace) -> int:
    """Entry point of `eqgw keys create`."""
    from app.api.auth import create_key

    engine = _engine(args)
    try:
        key_id, key = create_key(engine, args.name, args.role)
    finally:
        engine.dispose()
    print(f"created key {key_id} ({args.role}, {args.name!r}); it is shown only now:")
    print(key)
    return 0


def keys_list(args: argparse.Namespace) -> int:
    """Entry point of `eqgw keys list`."""
    from app.store import api_queries as q

    engine = _engine(args)
    try:
        with engine.connect() as conn:
            rows = q.list_keys(conn)
    finally:
        engine.dispose()
    print(f"{'id':>4}  {'role':<8}  {'prefix':<12}  {'state':<8}  {'last used':<20}  name")
    for r in rows:
        state = "revoked" if r["revoked_at"] else "active"
        used = (
            time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(r["last_used_at"]))
            if r["last_used_at"]
            else "never"
        )
        print(
            f"{r['id']:>4}  {r['role']:<8}  {r['prefix']:<12}  {state:<8}  {used:<20}  {r['name']}"
        )
    return 0


def keys_revoke(args: argparse.Namespace) -> int:
    """Entry point of `eqgw keys revoke`."""
    from app.store import api_queries as q

    engine = _engine(args)
    try:
        with engine.begin() as conn:
            done = q.revoke_key(conn, args.id, time.time())
    finally:
        engine.dispose()
    if not done:
        print(f"eqgw: no active key {args.id}", file=sys.stderr)
        return 1
    print(f"revoked key {args.id} (a running server stops accepting it within seconds)")
    return 0
