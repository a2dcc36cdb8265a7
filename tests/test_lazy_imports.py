"""What a gateway does not load at its start: the HTTP stack of webhooks (httpx, httpcore)
until it first delivers one, the OpenID Connect libraries (authlib, joserfc) unless single
sign-on is set up. Checked in fresh interpreters, which import what a gateway process does."""

from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path

LAZY = ("httpx", "httpcore", "authlib", "joserfc")

_START = """
import asyncio, sys
from eqgw.config import Settings
from eqgw.main import create_app
from eqgw.web.settings import ApiSettings

LAZY = sys.argv[3].split(",")
groups = {"ops": {"role": "viewer", "all": True}}
sso = {"issuer": "https://idp.example", "client_id": "eqgw", "groups": groups}
oidc = sso if sys.argv[2] == "sso" else {}
app = create_app(Settings(database_url=sys.argv[1], oidc=oidc), api=ApiSettings())
print("loaded:", " ".join(m for m in LAZY if m in sys.modules))
if sys.argv[2] == "webhook":
    from eqgw.notify.delivery import http_client

    async def first_client():
        client = await http_client(())
        await client.aclose()
        return type(client).__name__

    print("client:", asyncio.run(first_client()))
    print("loaded:", " ".join(m for m in LAZY if m in sys.modules))
"""


def _start(tmp_path: Path, mode: str) -> list[str]:
    done = subprocess.run(
        [
            sys.executable,
            "-c",
            textwrap.dedent(_START),
            f"sqlite:///{tmp_path / 'eqgw.db'}",
            mode,
            ",".join(LAZY),
        ],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 0, done.stderr
    return done.stdout.splitlines()


def test_a_start_loads_neither_the_webhook_http_stack_nor_single_sign_on(tmp_path: Path) -> None:
    assert _start(tmp_path, "plain") == ["loaded: "]


def test_single_sign_on_set_up_loads_its_libraries(tmp_path: Path) -> None:
    (line,) = _start(tmp_path, "sso")
    loaded = line.removeprefix("loaded: ").split()
    assert {"authlib", "joserfc", "httpx"} <= set(loaded), loaded


def test_the_first_webhook_client_loads_the_http_stack(tmp_path: Path) -> None:
    assert _start(tmp_path, "webhook") == [
        "loaded: ",
        "client: AsyncClient",
        "loaded: httpx httpcore",
    ]
