"""`eqgw serve` (ingest + API in one process) and `eqgw keys` (create, list, revoke, ...)."""

from __future__ import annotations

import argparse
import contextlib
import faulthandler
import math
import os
import signal
import socket
import sys
import threading
import time
from collections.abc import Callable, Iterator
from types import FrameType
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from sqlalchemy import Engine


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
    p.add_argument(
        "--access-log",
        action="store_true",
        default=os.environ.get("EQGW_ACCESS_LOG", "") not in ("", "0", "false"),
        help="log every HTTP request at info (API keys in URLs are masked; or EQGW_ACCESS_LOG=1)",
    )
    p.set_defaults(func=serve)

    k = subparsers.add_parser(
        "keys",
        help="manage API keys",
        description="Keys live in the database: run these with the server's --config or --db "
        "(the default is eqgw.db in the current folder).",
    )
    _database_options(k, top=True)
    ksub = k.add_subparsers(dest="keys_command", metavar="ACTION")
    c = ksub.add_parser("create", help="create a key and print it (shown once)")
    _database_options(c, top=False)
    c.add_argument(
        "--role",
        required=True,
        choices=("viewer", "operator", "admin", "ingest"),
        help="viewer < operator < admin; ingest only posts forwarded frames (eqgw forward)",
    )
    c.add_argument("--name", required=True, type=_key_name, help="who or what holds the key")
    c.add_argument(
        "--group",
        action="append",
        metavar="DEPOT",
        help="limit the key to this depot's vehicles (repeatable; with --vehicle: either)",
    )
    c.add_argument(
        "--vehicle",
        action="append",
        metavar="ID",
        help="limit the key to this vehicle (repeatable); an ingest key uploads only for these",
    )
    c.add_argument(
        "--all-vehicles",
        action="store_true",
        help="every vehicle (the default for other roles); an ingest key needs this, --vehicle "
        "or --group: a fleet-wide forwarder key, if leaked, uploads for any vehicle",
    )
    c.add_argument("--expires-in", type=_expiry, metavar="DURATION", help=_DURATION_HELP)
    c.set_defaults(func=keys_create)
    ls = ksub.add_parser("list", help="list keys (never the keys themselves)")
    _database_options(ls, top=False)
    ls.set_defaults(func=keys_list)
    r = ksub.add_parser("revoke", help="revoke a key by id")
    r.add_argument("id", type=int)
    _database_options(r, top=False)
    r.set_defaults(func=keys_revoke)
    rot = ksub.add_parser(
        "rotate",
        help="replace a key: print a new one like it; the old one works for --overlap more",
    )
    rot.add_argument("id", type=int)
    _database_options(rot, top=False)
    rot.add_argument(
        "--overlap",
        type=_overlap,
        default=86400.0,
        metavar="DURATION",
        help="how long the old key keeps working (default 1d, at most 30d; 0 revokes it at once)",
    )
    rot.add_argument("--expires-in", type=_expiry, metavar="DURATION", help=_DURATION_HELP)
    rot.add_argument(
        "--group", action="append", metavar="DEPOT", help="narrow the new key to this depot"
    )
    rot.add_argument(
        "--vehicle", action="append", metavar="ID", help="narrow the new key to this vehicle"
    )
    rot.set_defaults(func=keys_rotate)
    link = ksub.add_parser(
        "login-link",
        help="print a one-time dashboard login link for a key (the key itself is not shown)",
        description="A link that logs a browser in to the dashboard as key ID once, within "
        "EQGW_API_LOGIN_CODE_TTL_S (default 10 min), on any gateway of the database. The "
        "address is EQGW_API_PUBLIC_URL, else http://EQGW_API_HOST:EQGW_API_PORT.",
    )
    link.add_argument("id", type=int)
    _database_options(link, top=False)
    link.set_defaults(func=keys_login_link)
    k.set_defaults(func=lambda _args: _help(k))


def _database_options(parser: argparse.ArgumentParser, top: bool) -> None:
    # Accepted before and after the action (`eqgw keys --config f list`, `eqgw keys list
    # --config f`): the action's copies default to nothing so they never undo the parent's.
    default = None if top else argparse.SUPPRESS
    parser.add_argument(
        "--config", metavar="FILE", default=default, help="TOML fleet file (or EQGW_CONFIG)"
    )
    parser.add_argument(
        "--db", metavar="URL", default=default, help="database URL (overrides the settings)"
    )


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
    from eqgw.security.keys import check_key_name

    try:
        return check_key_name(value)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


_DURATION_HELP = (
    "expire the key after this long (a minute to ten years): seconds, or a number with s, m, h or d"
)
_UNITS = {"s": 1.0, "m": 60.0, "h": 3600.0, "d": 86400.0}


def _duration(value: str) -> float:
    """`90`, `90s`, `15m`, `12h` or `30d` as seconds."""
    text = value.strip().lower()
    factor = _UNITS.get(text[-1:], None)
    number = text[:-1] if factor is not None else text
    try:
        seconds = float(number) * (factor or 1.0)
    except ValueError:
        seconds = math.nan
    if not math.isfinite(seconds):
        raise argparse.ArgumentTypeError(f"{value!r} is not a duration (e.g. 90, 15m, 30d)")
    return seconds


def _expiry(value: str) -> float:
    """A key's life: a duration from a minute to ten years (the API's bounds)."""
    from eqgw.security.schemas import MAX_KEY_LIFE_S, MIN_KEY_LIFE_S

    seconds = _duration(value)
    if not MIN_KEY_LIFE_S <= seconds <= MAX_KEY_LIFE_S:
        raise argparse.ArgumentTypeError(
            f"{value!r} is not between a minute and ten years (a key that expires sooner "
            "would lock its holder out)"
        )
    return seconds


def _overlap(value: str) -> float:
    """A rotation's overlap: a duration from 0 (the old key revoked at once) to 30 days."""
    from eqgw.security.schemas import MAX_OVERLAP_S

    seconds = _duration(value)
    if not 0 <= seconds <= MAX_OVERLAP_S:
        raise argparse.ArgumentTypeError(f"{value!r} is not between 0 and 30 days")
    return seconds


def _help(parser: argparse.ArgumentParser) -> int:
    parser.print_help()
    return 2


def _settings(args: argparse.Namespace) -> object:
    from eqgw.config import ConfigError, load_settings

    overrides = {"database_url": args.db} if getattr(args, "db", None) else {}
    try:
        return load_settings(getattr(args, "config", None), **overrides)
    except ConfigError as exc:
        print(f"eqgw: {exc}", file=sys.stderr)
        raise SystemExit(2) from exc


def serve(args: argparse.Namespace) -> int:
    """Entry point of `eqgw serve`."""
    import uvicorn

    from eqgw.config import Settings
    from eqgw.describe import describe
    from eqgw.main import SERVER_SHUTDOWN_S, create_app
    from eqgw.web.settings import ApiSettings

    # A hangup (a closed terminal, `systemctl reload`, `kill -HUP`) would end the process
    # with no word: it is said and otherwise ignored (settings are read at start only; the
    # fleet is followed in the database: eqgw.fleet.sync).
    signal.signal(signal.SIGHUP, _hangup)
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
        print(
            f"eqgw: cannot listen on {api.host}:{api.port}: {exc.strerror or exc}", file=sys.stderr
        )
        return 2
    api = api.model_copy(update={"port": sock.getsockname()[1]})  # the real one, for --port 0
    if not _wait_for_database(settings.database_url):
        sock.close()
        return 2
    sim = None
    if args.simulate:
        from eqgw.sim.clock import RealtimeClock
        from eqgw.sim.fleet import SimulatedFleet

        sim = SimulatedFleet(args.simulate, seed=args.seed, clock=RealtimeClock())
    host = f"[{api.host}]" if ":" in api.host else api.host
    base = api.public_url or f"http://{host}:{api.port}"

    def show_first_key(key: str) -> None:
        # The only time this key is ever shown; it is for API clients, never put in a link.
        print(
            "eqgw: first start, created an admin key for the API (shown once, store it now):",
            flush=True,
        )
        print(f"    {key}", flush=True)
        print(f"eqgw: API docs at {base}/docs", flush=True)

    def show_login_link(code: str) -> None:
        from eqgw.security.login_codes import login_link

        minutes = f"{api.login_code_ttl_s / 60:g} min"
        print(f"eqgw: log in to the dashboard: {login_link(base, code)}", flush=True)
        print(
            f"      (works once, within {minutes}; a new link: eqgw keys login-link 1)", flush=True
        )

    def ready() -> None:
        print(
            f"eqgw: serving on {base} ({len(app.state.settings.buses)} buses"
            + (f", {args.simulate} simulated vehicles" if args.simulate else "")
            + ")",
            flush=True,
        )

    fatal: list[str] = []

    def end(exc: Exception) -> None:
        # A background task met a fault that will not heal: one line, then a clean shutdown
        # and a non-zero exit, for systemd or Docker to restart and an operator to read.
        if not fatal:
            fatal.append(describe(exc))
            print(f"eqgw: stopping, {exc} will not heal by retrying", file=sys.stderr, flush=True)
            signal.raise_signal(signal.SIGTERM)

    lost: list[int] = []

    def stopped(left: int) -> None:
        if left:
            # Neither the database nor a journal took them: said loudly, and the exit status
            # is not 0, for an operator (or systemd) to see.
            lost.append(left)
            print(f"eqgw: stopping: final flush left {left} rows unwritten, LOST", flush=True)
            print(f"eqgw: {left} rows lost at stop", file=sys.stderr, flush=True)
        else:
            print("eqgw: stopping: final flush done, every row written", flush=True)

    app = create_app(
        settings,
        api=api,
        sim=sim,
        on_first_key=show_first_key,
        on_login_code=show_login_link,
        on_stopped=stopped,
        on_fatal=end,
    )
    # uvicorn's records go through the process's logging (eqgw.logs): same format, keys masked.
    from eqgw.api.http_protocol import bounded_h11

    config = uvicorn.Config(
        app,
        http=bounded_h11(api.header_timeout_s),
        log_config=None,
        access_log=args.access_log,
        ws="websockets-sansio",
        timeout_graceful_shutdown=SERVER_SHUTDOWN_S,
    )
    if args.access_log:
        import logging

        logging.getLogger("uvicorn.access").setLevel(logging.INFO)
    _bounded_server(config, api.shutdown_timeout_s, ready, lambda: bool(lost)).run(sockets=[sock])
    return 1 if fatal or lost else 0


def _hangup(_sig: int, _frame: FrameType | None) -> None:
    import logging

    logging.getLogger("eqgw.serve").warning(
        "SIGHUP ignored: settings are read at start only (restart eqgw serve to apply them); "
        "vehicles and buses are managed in the database without a restart "
        "(/api/v1/vehicles, eqgw vehicles import)"
    )


def _bounded_server(
    config: Any,
    limit: float,
    on_listening: Callable[[], None],
    failed: Callable[[], bool] = lambda: False,
) -> Any:
    """uvicorn's server, saying so once it accepts connections (the lifespan's startup ends
    before uvicorn listens, so a line printed from it could send a client to a refusal), and
    whose first stop signal also starts a watchdog: a shutdown still running after `limit`
    seconds dumps every thread's stack and ends the process (exit 3), so a stop never outlasts
    a container's stop timeout and ends in SIGKILL with no word. A stop that `failed()` (rows
    lost) exits with status 1 rather than by the signal."""
    import uvicorn

    class BoundedServer(uvicorn.Server):
        def __init__(self) -> None:
            super().__init__(config)
            self._watchdog: threading.Thread | None = None

        async def startup(self, sockets: list[socket.socket] | None = None) -> None:
            await super().startup(sockets)
            if self.started and not self.should_exit:
                on_listening()

        @contextlib.contextmanager
        def capture_signals(self) -> Iterator[None]:
            # uvicorn ends the process with the stop signal it caught, once stopped; a stop
            # that failed (rows lost) ends with a non-zero status instead, which says so.
            with super().capture_signals():
                yield
                if failed():
                    self._captured_signals.clear()

        def handle_exit(self, sig: int, frame: FrameType | None) -> None:
            if self._watchdog is None:
                self._watchdog = threading.Thread(
                    target=_end_after, args=(limit,), name="eqgw shutdown watchdog", daemon=True
                )
                self._watchdog.start()
            super().handle_exit(sig, frame)

    return BoundedServer()


def _end_after(limit: float) -> None:
    time.sleep(limit)
    print(
        f"eqgw: shutdown still running after {limit:g} s: exiting now; stacks follow",
        file=sys.stderr,
        flush=True,
    )
    faulthandler.dump_traceback(file=sys.stderr, all_threads=True)
    os._exit(3)


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

    from eqgw.describe import describe
    from eqgw.store.engine import create_engine
    from eqgw.tasks import Backoff, permanent_fault

    if url.startswith("sqlite"):
        path = make_url(url).database
        folder = os.path.dirname(os.path.abspath(path)) if path else ""
        if path and path != ":memory:" and not os.path.isdir(folder):
            print(
                f"eqgw: the folder of the SQLite database {path!r} does not exist", file=sys.stderr
            )
            return False
    backoff = Backoff(1.0, 30.0, jitter=False)
    while True:
        engine = create_engine(url)
        try:
            with engine.connect() as conn:
                conn.execute(text("SELECT 1"))
            if engine.dialect.name == "sqlite":
                # Reading is not enough: a read-only file fails only when it is to be written.
                with engine.execution_options(sqlite_begin="IMMEDIATE").connect() as conn:
                    version = conn.exec_driver_sql("PRAGMA user_version").scalar()
                    conn.exec_driver_sql(f"PRAGMA user_version = {int(version or 0)}")
                    conn.rollback()
            return True
        except SQLAlchemyError as exc:
            if permanent_fault(exc):
                print(f"eqgw: the database cannot be used: {describe(exc)}", file=sys.stderr)
                return False
            delay = backoff.next()
            print(
                f"eqgw: the database is unreachable ({describe(exc)}); retrying in {delay:g} s",
                file=sys.stderr,
                flush=True,
            )
        finally:
            engine.dispose()
        time.sleep(delay)


def _engine(args: argparse.Namespace) -> Engine:
    """The migrated database of the settings; one line and exit 1 when it cannot be."""
    from sqlalchemy.exc import SQLAlchemyError

    from eqgw.config import Settings
    from eqgw.describe import describe
    from eqgw.store.engine import create_engine
    from eqgw.store.errors import MigrationError
    from eqgw.store.migrate import upgrade_engine

    settings = _settings(args)
    assert isinstance(settings, Settings)
    _say_if_new_sqlite(settings.database_url)
    engine = create_engine(settings.database_url)
    try:
        upgrade_engine(engine)
    except (SQLAlchemyError, MigrationError, OSError) as exc:
        engine.dispose()
        # A MigrationError's first line carries its cause's (the driver's) message.
        print(f"eqgw: the database cannot be used: {describe(exc)}", file=sys.stderr)
        raise SystemExit(1) from exc
    return engine


def _say_if_new_sqlite(url: str) -> None:
    """Keys are kept in the database: one made in a new SQLite file (the wrong folder, no
    --config) is a key no running server knows. Said before the file is created."""
    from sqlalchemy.engine import make_url

    if not url.startswith("sqlite"):
        return
    path = make_url(url).database
    if not path or path == ":memory:" or os.path.exists(path):
        return
    print(
        f"eqgw: warning: no database at {os.path.abspath(path)}: creating a new, empty one. "
        "A server that uses another database will not know its keys: run this with the "
        "server's --config or --db URL.",
        file=sys.stderr,
    )


def keys_create(args: argparse.Namespace) -> int:
    """Entry point of `eqgw keys create`."""
    from eqgw.security.keys import EVERYTHING, Scope, create_key

    scope = EVERYTHING
    if args.group or args.vehicle:
        if args.all_vehicles:
            print(
                "eqgw: --all-vehicles is every vehicle: give no --vehicle or --group with it",
                file=sys.stderr,
            )
            return 2
        scope = Scope.of(args.group or [], args.vehicle or [])
    elif args.role == "ingest" and not args.all_vehicles:
        print(
            "eqgw: an ingest key needs the vehicles its forwarder uploads for: --vehicle ID or "
            "--group DEPOT (repeatable), or --all-vehicles for a relay that uploads for every "
            "vehicle (such a key, if leaked, forges any vehicle's frames)",
            file=sys.stderr,
        )
        return 2
    expires_at = time.time() + args.expires_in if args.expires_in is not None else None
    engine = _engine(args)
    try:
        key_id, key = create_key(engine, args.name, args.role, scope=scope, expires_at=expires_at)
    finally:
        engine.dispose()
    print(
        f"created key {key_id} ({args.role}, {args.name!r}, "
        f"{_scope_text(scope.as_json(), args.role)}"
        f"{_expiry_text(expires_at)}); it is shown only now:"
    )
    print(key)
    return 0


def _scope_text(scope: dict[str, list[str]] | None, role: str | None = None) -> str:
    if scope is None:
        # A fleet-wide ingest key uploads for every vehicle: shown so it stands out.
        return "ALL VEHICLES" if role == "ingest" else "all vehicles"
    parts = [f"depot {g}" for g in scope["groups"]] + list(scope["vehicles"])
    return ", ".join(parts)


def _when(ts: float) -> str:
    return time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(ts))


def _expiry_text(expires_at: float | None) -> str:
    return "" if expires_at is None else f", expires {_when(expires_at)}"


def keys_rotate(args: argparse.Namespace) -> int:
    """Entry point of `eqgw keys rotate`."""
    from eqgw.config import Settings
    from eqgw.fleet.registry import in_effect
    from eqgw.security.keys import KeyNotFound, Scope, rotate_key

    settings = _settings(args)
    assert isinstance(settings, Settings)
    settings = in_effect(settings)  # the database's vehicles, once it has them
    fleet = Scope(depots={v.id: v.depot for v in settings.vehicles})  # resolves depots
    expires_at = time.time() + args.expires_in if args.expires_in is not None else None
    scope = Scope.of(args.group or [], args.vehicle or []) if args.group or args.vehicle else None
    engine = _engine(args)
    try:
        new_id, key, ends = rotate_key(
            engine,
            args.id,
            overlap_s=args.overlap,
            expires_at=expires_at,
            scope=scope,
            within=fleet,
        )
    except KeyNotFound:
        print(f"eqgw: no active key {args.id}", file=sys.stderr)
        return 1
    except ValueError as exc:
        print(f"eqgw: {exc}", file=sys.stderr)
        return 2
    finally:
        engine.dispose()
    print(
        f"created key {new_id} to replace key {args.id}{_expiry_text(expires_at)}; "
        "it is shown only now:"
    )
    print(key)
    print(f"key {args.id} keeps working until {_when(ends)}, then is revoked")
    return 0


def keys_login_link(args: argparse.Namespace) -> int:
    """Entry point of `eqgw keys login-link`."""
    from eqgw.security import repository as q
    from eqgw.security.keys import INGEST, key_active
    from eqgw.security.login_codes import create_login_code, login_link
    from eqgw.web.settings import ApiSettings

    api = ApiSettings()
    host = f"[{api.host}]" if ":" in api.host else api.host
    base = api.public_url or f"http://{host}:{api.port}"
    engine = _engine(args)
    try:
        with engine.connect() as conn:
            row = q.get_key(conn, args.id)
        if row is None or not key_active(row, time.time()):
            print(f"eqgw: no active key {args.id}", file=sys.stderr)
            return 1
        if row["role"] == INGEST:
            print(f"eqgw: key {args.id} is an ingest key: it cannot log in", file=sys.stderr)
            return 2
        # A transaction of its own that writes first: on SQLite beside a running gateway, a
        # read that then writes cannot wait for the write lock ("database is locked" at once);
        # a first write waits its busy timeout. (A key revoked meanwhile: its code logs no one
        # in, the exchange checks the key.)
        with engine.begin() as conn:
            code = create_login_code(conn, args.id, api.login_code_ttl_s)
    finally:
        engine.dispose()
    print(
        f"one-time dashboard login as key {args.id} ({row['role']}, {row['name']!r}), "
        f"within {api.login_code_ttl_s / 60:g} min:"
    )
    print(login_link(base, code))
    return 0


def keys_list(args: argparse.Namespace) -> int:
    """Entry point of `eqgw keys list`."""
    from eqgw.security import repository as q

    engine = _engine(args)
    try:
        with engine.connect() as conn:
            rows = q.list_keys(conn)
    finally:
        engine.dispose()
    from eqgw.security.keys import key_active, scope_of

    now = time.time()
    print(
        f"{'id':>4}  {'role':<8}  {'prefix':<12}  {'state':<8}  {'last used':<19}  "
        f"{'ends':<19}  {'scope':<20}  name"
    )
    for r in rows:
        ends = min((t for t in (r["revoked_at"], r["expires_at"]) if t is not None), default=None)
        if key_active(r, now):
            state = "active"
        elif r["expires_at"] is not None and r["expires_at"] <= now and ends == r["expires_at"]:
            state = "expired"
        else:
            state = "revoked"
        used = _when(r["last_used_at"]) if r["last_used_at"] else "never"
        until = _when(ends) if ends is not None else "never"
        scope = _scope_text(scope_of(r).as_json(), r["role"])
        print(
            f"{r['id']:>4}  {r['role']:<8}  {r['prefix']:<12}  {state:<8}  {used:<19}  "
            f"{until:<19}  {scope:<20}  {r['name']}"
        )
    return 0


def keys_revoke(args: argparse.Namespace) -> int:
    """Entry point of `eqgw keys revoke`."""
    from eqgw.security import repository as q

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
