"""A real OpenID provider on loopback for the single sign-on tests: tests/oidc/provider.js
(panva/oidc-provider, installed by `npm ci --prefix tests/oidc`) as a child process."""

from __future__ import annotations

import contextlib
import json
import os
import select
import shutil
import subprocess
import time
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

import pytest

OIDC_DIR = Path(__file__).resolve().parent / "oidc"
SECRET = "eqgw-test-secret"  # every client's (tests/oidc/provider.js)


def provider_unavailable_reason() -> str | None:
    """Why the provider cannot run here (None: it can)."""
    if shutil.which("node") is None:
        return "node is not installed: the single sign-on tests run a real OpenID provider on it"
    version = subprocess.run(["node", "--version"], capture_output=True, text=True).stdout
    if int(version.lstrip("v").split(".")[0] or 0) < 20:
        return f"node {version.strip()} is too old for the test OpenID provider (20 or later)"
    if not (OIDC_DIR / "node_modules" / "oidc-provider").is_dir():
        return "the test OpenID provider is not installed: run npm ci --prefix tests/oidc"
    return None


@contextlib.contextmanager
def running_provider(
    users: Mapping[str, Mapping[str, Any]],
    redirect_uris: list[str],
    *,
    conform: bool = False,
    log: Path | None = None,
) -> Iterator[str]:
    """The provider with these accounts and clients registering `redirect_uris`, listening
    on a free port of 127.0.0.1; its issuer URL. With `conform`, claims asked for by scope
    (email, groups) come from the UserInfo endpoint only."""
    reason = provider_unavailable_reason()
    if reason:
        pytest.skip(reason)
    env = {
        **os.environ,
        "OIDC_USERS": json.dumps(users),
        "OIDC_REDIRECT_URIS": json.dumps(redirect_uris),
        "OIDC_CONFORM": "1" if conform else "0",
    }
    with contextlib.ExitStack() as stack:
        err = stack.enter_context(open(log, "wb")) if log else subprocess.DEVNULL
        proc = subprocess.Popen(
            ["node", "provider.js"], cwd=OIDC_DIR, env=env, stdout=subprocess.PIPE, stderr=err
        )
        try:
            assert proc.stdout is not None
            deadline = time.monotonic() + 30
            line = b""
            while not line.endswith(b"\n"):
                left = deadline - time.monotonic()
                assert left > 0 and proc.poll() is None, "the OpenID provider did not start"
                ready, _, _ = select.select([proc.stdout], [], [], left)
                if ready:
                    chunk = os.read(proc.stdout.fileno(), 4096)
                    assert chunk, "the OpenID provider exited before it was ready"
                    line += chunk
            issuer: str = json.loads(line)["issuer"]
            yield issuer
        finally:
            proc.terminate()
            try:
                proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(timeout=10)
            if proc.stdout is not None:
                proc.stdout.close()
