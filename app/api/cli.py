"""`eqgw serve` (ingest + API in one process) and `eqgw keys create|list|revoke`."""

from __future__ import annotations

import argparse
import os
import socket
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
    p.add_argument(
        "--port", type=_port, help="port, 0 for any free one (default EQGW_API_PORT or 8000)"
    )
    p.add_argument(
        "--simulate",
        type=_count,
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
    c.add_argument("--name", required=True, type=_key_name, help="who or what holds the key")
    c.set_defaults(func=keys_create)
    ls = ksub.add_parser("list", help="list keys (never the keys themselves)")
    ls.set_defaults(func=keys_list)
    r = ksub.add_parser("revoke", help="revoke a key by id")
    r.add_argument("id", type=int)
    r.set_defaults(func=keys_revoke)
    k.set_defaults(func=lambda _args: _help(k))


def _port(value: str) -> int:
    try:
        port = int(value)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{value!r} is not a port number") from None
    if not 0 <= port <= 65535:
        raise argparse.ArgumentTypeError(f"{port} is not a port (0-65535)")
    return port


def _count(value: str) -> int:
    try:
        n = int(value)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{value!r} is not a whole number") from None
    if n < 0:
        raise argparse.ArgumentTypeError(f"{n} is negative")
    return n


def _key_name(value: str) -> str:
    from app.api.auth import check_key_name

    try:
        return check_key_name(value)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


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
    # The address first: a port in use or a bad host is said before anything is created
    # (the one-time admin key above all), not after it was printed.
    try:
        sock = _listen(api.host, api.port)
    except OSError as exc:
        print(f"eqgw: cannot listen on {api.host}:{api.port}: {exc.strerror or exc}",
              file=sys.stderr)  # fmt: skip
        return 2
    api = api.model_copy(update={"port": sock.getsockname()[1]})  # the real one, for --port 0
    if not _wait_for_database(settings.database_url):
        sock.close()
        return 2
    sim = None
    if args.simulate:
        from app.sim.clock import RealtimeClock
        from app.sim.fleet import SimulatedFleet

        sim = SimulatedFleet(args.simulate, seed=args.seed, clock=RealtimeClock())
    host = f"[{api.host}]" if ":" in api.host else api.host
    base = api.public_url or f"http://{host}:{api.port}"

    def show_first_key(key: str) -> None:
        # Like Jupyter: the only time this key is ever shown.
        print("eqgw: first start, created an admin key (shown once, store it now):", flush=True)
        print(f"    {key}", flush=True)
        print(f"eqgw: open {base}/?key={key}", flush=True)
        print(f"eqgw: API docs at {base}/docs", flush=True)

    def ready() -> None:
        print(
            f"eqgw: serving on {base} ({len(app.state.settings.buses)} buses"
            + (f", {args.simulate} simulated vehicles" if args.simulate else "")
            + ")",
            flush=True,
        )

    app = create_app(settings, api=api, sim=sim, on_first_key=show_first_key, on_ready=ready)
    config = uvicorn.Config(app, log_level="warning", ws="websockets-sansio")
    uvicorn.Server(config).run(sockets=[sock])
    return 0


def _listen(host: str, port: int) -> socket.socket:
    """A TCP socket bound to (host, port), for uvicorn to listen on."""
    family, kind, proto, _, addr = socket.getaddrinfo(
        host, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE
    )[0]
    sock = socket.socket(family, kind, proto)
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.bind(addr)
    except OSError:
        sock.close()
        raise
    return sock


def _wait_for_database(url: str) -> bool:
    """Until the database answers: a server that is not up yet (or a network away) is
    retried with backoff and each failure said in one line; one that can never work (a
    SQLite file in a folder that does not exist) ends the start. False to give up."""
    from sqlalchemy import text
    from sqlalchemy.engine import make_url
    from sqlalchemy.exc import SQLAlchemyError

    from app.describe import describe
    from app.store.engine import create_engine

    if url.startswith("sqlite"):
        path = make_url(url).database
        folder = os.path.dirname(os.path.abspath(path)) if path else ""
        if path and path != ":memory:" and not os.path.isdir(folder):
            print(f"eqgw: the folder of the SQLite database {path!r} does not exist",
                  file=sys.stderr)  # fmt: skip
            return False
    delay = 1.0
    while True:
        engine = create_engine(url)
        try:
            with engine.connect() as conn:
                conn.execute(text("SELECT 1"))
            return True
        except SQLAlchemyError as exc:
            print(f"eqgw: the database is unreachable ({describe(exc)}); retrying in {delay:g} s",
                  file=sys.stderr, flush=True)  # fmt: skip
        finally:
            engine.dispose()
        time.sleep(delay)
        delay = min(delay * 2, 30.0)


def _engine(args: argparse.Namespace):  # type: ignore[no-untyped-def]
    """The migrated database of the settings; one line and exit 1 when it cannot be."""
    from sqlalchemy.exc import SQLAlchemyError

    from app.config import Settings
    from app.describe import describe
    from app.store.engine import create_engine
    from app.store.errors import MigrationError
    from app.store.migrate import upgrade_engine

    settings = _settings(args)
    assert isinstance(settings, Settings)
    engine = create_engine(settings.database_url)
    try:
        upgrade_engine(engine)
    except (SQLAlchemyError, MigrationError, OSError) as exc:
        engine.dispose()
        # A MigrationError's first line carries its cause's (the driver's) message.
        print(f"eqgw: the database cannot be used: {describe(exc)}", file=sys.stderr)
        raise SystemExit(1) from exc
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
