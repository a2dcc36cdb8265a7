"""Run a store function in one transaction: the one typed way, sync or in a worker thread.

Every query and write of the store takes a `Connection` first (`fn(conn, *args)`); these run
it inside `engine.begin()` (committed on return, rolled back on an exception) and keep its
parameter and return types, so a caller is checked against the function it runs.
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable
from typing import Concatenate, ParamSpec, TypeVar

from sqlalchemy import Connection, Engine

P = ParamSpec("P")
R = TypeVar("R")


def in_transaction(
    engine: Engine,
    fn: Callable[Concatenate[Connection, P], R],
    /,
    *args: P.args,
    **kwargs: P.kwargs,
) -> R:
    """`fn(conn, *args, **kwargs)` in one transaction of `engine`."""
    with engine.begin() as conn:
        return fn(conn, *args, **kwargs)


async def run_in_transaction(
    engine: Engine,
    fn: Callable[Concatenate[Connection, P], R],
    /,
    *args: P.args,
    **kwargs: P.kwargs,
) -> R:
    """`in_transaction` in a worker thread (from asyncio code)."""
    return await asyncio.to_thread(in_transaction, engine, fn, *args, **kwargs)
