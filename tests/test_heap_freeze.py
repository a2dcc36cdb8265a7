"""The gateway and the collector: a gateway freezes its startup heap when the heap is its own,
and leaves the collector alone in a process that froze its heap itself (eqgw.api.lifespan)."""

from __future__ import annotations

import gc
from collections.abc import Iterator
from pathlib import Path

import pytest
from fastapi import FastAPI

from eqgw.api.lifespan import GC_THRESHOLDS, host_manages_collector
from eqgw.config import Settings
from eqgw.main import create_app
from eqgw.sim.clock import RealtimeClock
from eqgw.sim.fleet import SimulatedFleet


@pytest.fixture
def thawed() -> Iterator[None]:
    """The test process's heap as a gateway process's is when it starts: nothing frozen,
    nothing said about the collector (frozen and said again afterwards, as the run keeps it:
    tests/conftest.py)."""
    said = host_manages_collector(False)
    gc.unfreeze()
    try:
        yield
    finally:
        gc.collect()
        gc.freeze()
        host_manages_collector(said)


@pytest.fixture
def unsaid() -> Iterator[None]:
    """Nothing said about the collector: a gateway looks for itself (said again afterwards)."""
    said = host_manages_collector(False)
    try:
        yield
    finally:
        host_manages_collector(said)


def _app(tmp_path: Path) -> FastAPI:
    sim = SimulatedFleet(1, seed=1, clock=RealtimeClock(4.0))
    return create_app(Settings(database_url=f"sqlite:///{tmp_path / 'eqgw.db'}"), sim=sim)


async def test_a_gateway_freezes_the_heap_it_owns_and_thaws_it_at_its_end(
    tmp_path: Path, thawed: None
) -> None:
    app = _app(tmp_path)
    before = gc.get_threshold()
    assert gc.get_freeze_count() == 0
    async with app.router.lifespan_context(app):
        assert gc.get_freeze_count() > 0, "startup's heap is not frozen"
        assert gc.get_threshold() == GC_THRESHOLDS
    assert gc.get_freeze_count() == 0, "the gateway left its heap frozen"
    assert gc.get_threshold() == before


async def test_a_gateway_leaves_a_heap_frozen_before_it_alone(tmp_path: Path, unsaid: None) -> None:
    frozen = gc.get_freeze_count()
    assert frozen > 0, "the run freezes its heap once the tests are collected"
    app = _app(tmp_path)
    before = gc.get_threshold()
    async with app.router.lifespan_context(app):
        assert gc.get_threshold() == before
        # No more frozen (the gateway froze nothing of its own); a few fewer: frozen objects
        # still die when nothing refers to them any more.
        assert frozen * 0.9 < gc.get_freeze_count() <= frozen
    assert frozen * 0.9 < gc.get_freeze_count() <= frozen, "the process's heap was thawed"
    assert gc.get_threshold() == before


async def test_a_host_that_says_it_manages_the_collector_is_left_alone(
    tmp_path: Path, thawed: None
) -> None:
    """Said, not looked at: nothing frozen, and the gateway still leaves the collector as it
    is (an application that manages the collector itself and has not frozen yet)."""
    host_manages_collector()
    app = _app(tmp_path)
    before = gc.get_threshold()
    async with app.router.lifespan_context(app):
        assert gc.get_freeze_count() == 0, "the gateway froze a heap it was told is not its own"
        assert gc.get_threshold() == before
    assert gc.get_threshold() == before
