"""Fault episodes of one unit from DM1, status flags, silence and a stuck heartbeat; parking."""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import TypeVar

from eqgw.ingest import events
from eqgw.jsontypes import JSONObject, as_float, as_int, as_object
from eqgw.store.writes import EpisodeValues

# Status flags that report a fault, and the fault name each shares with DM1 (SPEC-NOTES codes).
STATUS_FAULTS: dict[str, str] = {
    "ovf": "OVF",
    "uvf": "UVF",
    "imb": "IMB",
    "eqflt": "EQFLT",
    "ex24f": "EX24F",
    "ex12f": "EX12F",
    "exgnf": "EXGNF",
    "vcfl": "VCFL",
    "vcfh": "VCFH",
    "eq_battflt": "EQ_BATTFLT",
}
OFFLINE = "OFFLINE"
HEARTBEAT_STUCK = "HEARTBEAT_STUCK"

ACTIVE, STALE, CLOSED = "active", "stale", "closed"

# An episode's fields as its database row or as an event's JSON payload.
_Fields = TypeVar("_Fields", EpisodeValues, JSONObject)


@dataclass(slots=True)
class BusActivity:
    """What a unit's monitor knows of its whole bus: every node's frames count, not only the
    equalizers' (the engine, the transmission, other devices)."""

    silent_after_s: float = 6.0  # no frame on the bus for this long: the bus is silent
    heard: float = float("-inf")  # the bus's latest frame (any node)
    active_since: float = float("-inf")  # its first frame after its latest silence

    def on_frame(self, ts: float) -> None:
        heard = self.heard
        if ts > heard:
            if ts - heard > self.silent_after_s:
                self.active_since = ts
            self.heard = ts


def dtc_fault(dtc: JSONObject) -> str:
    """The fault name of a DTC: its SPEC-NOTES code, else SPN/FMI."""
    code = dtc.get("code")
    return str(code) if code else f"SPN{dtc.get('spn')}/FMI{dtc.get('fmi')}"


def dtcs_of(dm1: JSONObject) -> list[JSONObject]:
    """The DTCs a decoded DM1 lists (`eqgw.protocol.dm1.decode_dm1`'s `dtcs`)."""
    listed = dm1.get("dtcs")
    if not isinstance(listed, list):
        return []
    return [dtc for dtc in map(as_object, listed) if dtc is not None]


@dataclass(slots=True)
class Episode:
    """One fault episode; `row()` is its database row, `to_dict()` its event payload."""

    fault: str
    started_at: float
    last_seen_at: float
    sources: set[str] = field(default_factory=set)
    state: str = ACTIVE
    ended_at: float | None = None
    ended_by: str | None = None
    occurrence_count: int | None = None
    spn: int | None = None
    fmi: int | None = None

    @property
    def source(self) -> str:
        return "+".join(sorted(self.sources))

    def row(self) -> EpisodeValues:
        return self._fields(EpisodeValues)

    def to_dict(self) -> JSONObject:
        """The episode as an event's payload: its row's fields."""
        return self._fields(dict)

    def _fields(self, kind: type[_Fields]) -> _Fields:
        """A new dict of the episode's fields. `kind` only names the type wanted: mypy checks
        this one dict against each of them (the row's TypedDict and a JSON object)."""
        return {
            "fault": self.fault,
            "spn": self.spn,
            "fmi": self.fmi,
            "source": self.source,
            "state": self.state,
            "started_at": self.started_at,
            "last_seen_at": self.last_seen_at,
            "ended_at": self.ended_at,
            "ended_by": self.ended_by,
            "occurrence_count": self.occurrence_count,
        }


def _restored(row: Mapping[str, object]) -> Episode:
    """An open episode from its database row (`fault_episodes`)."""
    started_at = as_float(row["started_at"])
    last_seen_at = as_float(row["last_seen_at"])
    if started_at is None or last_seen_at is None:
        raise TypeError(f"an episode row without its times: {row!r}")
    return Episode(
        fault=str(row["fault"]),
        started_at=started_at,
        last_seen_at=last_seen_at,
        sources=set(str(row["source"]).split("+")),
        state=str(row["state"]),
        occurrence_count=as_int(row.get("occurrence_count")),
        spn=as_int(row.get("spn")),
        fmi=as_int(row.get("fmi")),
    )


Change = tuple[str, Episode]  # (event kind, episode after the change)


@dataclass(slots=True)
class _FaultInputs:
    dm1: bool = False  # listed in the latest DM1
    dm1_last: float = 0.0
    status: bool = False  # its status flag is active


class FaultTracker:
    """Opens, updates, marks stale and closes the episodes of one unit; pure, clock-driven."""

    def __init__(
        self,
        *,
        offline_after_s: float = 10.0,
        dm1_stale_after_s: float = 5.0,
        heartbeat_stuck_after: int = 3,
    ) -> None:
        self.offline_after_s = offline_after_s
        self.dm1_stale_after_s = dm1_stale_after_s
        self.heartbeat_stuck_after = heartbeat_stuck_after
        self.open: dict[str, Episode] = {}
        self.episode_counts: dict[str, int] = {}  # eqgw's own count of episodes per fault
        self._inputs: dict[str, _FaultInputs] = {}
        self._last_frame: float | None = None
        # Restored after a restart: silence counts only once the unit's bus is open again
        # (`on_bus_open`), from then on; a bus not yet open says nothing about its units.
        self._awaiting_bus = False
        self._watch_from: float | None = None
        self._heartbeat: int | None = None
        self._heartbeat_repeats = 0
        # Parked: the unit fell silent with its whole bus (ignition off), at this time (its
        # bus's last frame). No OFFLINE episode opens; the unit's next frame ends it, or,
        # once the bus carries traffic again, the offline window passing without one.
        self.parked_since: float | None = None

    # -- episode bookkeeping -------------------------------------------------------------

    def _start(self, fault: str, ts: float, source: str, out: list[Change]) -> Episode:
        ep = self.open.get(fault)
        if ep is None:
            ep = Episode(fault=fault, started_at=ts, last_seen_at=ts, sources={source})
            self.open[fault] = ep
            self.episode_counts[fault] = self.episode_counts.get(fault, 0) + 1
            out.append((events.FAULT_OPEN, ep))
            return ep
        changed = False
        if source not in ep.sources:
            ep.sources.add(source)
            changed = True
        if ep.state == STALE:
            ep.state = ACTIVE
            changed = True
        ep.last_seen_at = max(ep.last_seen_at, ts)
        if changed:
            out.append((events.FAULT_UPDATE, ep))
        return ep

    def _close(self, fault: str, ts: float, by: str, out: list[Change]) -> None:
        ep = self.open.pop(fault, None)
        if ep is None:
            return
        ep.state = CLOSED
        ep.ended_at = ts
        ep.ended_by = by
        out.append((events.FAULT_CLOSE, ep))

    def _inputs_of(self, fault: str) -> _FaultInputs:
        inp = self._inputs.get(fault)
        if inp is None:
            inp = self._inputs[fault] = _FaultInputs()
        return inp

    def restore(
        self,
        rows: Iterable[Mapping[str, object]],
        last_frame: float | None,
        heartbeat: int | None,
    ) -> None:
        """Take back the episodes still open in the database (active or stale) after a
        restart, so they continue instead of being opened again. `last_frame` is the unit's
        last frame time, `heartbeat` its last heartbeat value (a stuck one stays stuck)."""
        for row in rows:
            ep = _restored(row)
            fault = ep.fault
            self.open[fault] = ep
            self.episode_counts.setdefault(fault, 1)
            if "dm1" in ep.sources:
                inp = self._inputs_of(fault)
                inp.dm1 = True
                inp.dm1_last = ep.last_seen_at
            if "status" in ep.sources:
                self._inputs_of(fault).status = True
        if last_frame is not None:
            self._last_frame = last_frame
        self._awaiting_bus = True
        if HEARTBEAT_STUCK in self.open and heartbeat is not None:
            self._heartbeat = heartbeat
            self._heartbeat_repeats = self.heartbeat_stuck_after

    # -- inputs ----------------------------------------------------------------------------

    def on_bus_open(self, ts: float) -> None:
        """The unit's bus is open (its first frame, or the reader says so) at `ts`: a unit
        restored after a restart is offline once silent for the offline window from then."""
        if self._awaiting_bus:
            self._awaiting_bus = False
            self._watch_from = ts

    def on_frame(self, ts: float) -> list[Change]:
        """Any frame from the unit: it is online."""
        out: list[Change] = []
        self._awaiting_bus = False
        self.parked_since = None
        if self._last_frame is None or ts > self._last_frame:
            self._last_frame = ts
        if OFFLINE in self.open:
            self._close(OFFLINE, ts, "frame", out)
        return out

    def on_dm1(self, ts: float, fields: JSONObject) -> list[Change]:
        """A DM1: listed DTCs are active; every other DM1-reported fault has cleared."""
        out: list[Change] = []
        listed: dict[str, JSONObject] = {}
        for dtc in dtcs_of(fields):
            listed[dtc_fault(dtc)] = dtc
        for fault, dtc in listed.items():
            inp = self._inputs_of(fault)
            inp.dm1 = True
            inp.dm1_last = ts
            ep = self._start(fault, ts, "dm1", out)
            ep.spn, ep.fmi = as_int(dtc.get("spn")), as_int(dtc.get("fmi"))
            oc = as_int(dtc.get("oc"))
            if oc is not None and oc != ep.occurrence_count:
                ep.occurrence_count = oc
                if not out or out[-1][1] is not ep:
                    out.append((events.FAULT_UPDATE, ep))
        clear_by = "dm1_all_clear" if not listed else "dm1"
        for fault, inp in self._inputs.items():
            if inp.dm1 and fault not in listed:
                inp.dm1 = False
                if not inp.status:
                    self._close(fault, ts, clear_by, out)
        return out

    def on_status(self, ts: float, fields: JSONObject) -> list[Change]:
        """Status flags: `active` asserts a fault, `active` -> `inactive` clears it."""
        out: list[Change] = []
        for flag, fault in STATUS_FAULTS.items():
            value = fields.get(flag)
            if value == "active":
                self._inputs_of(fault).status = True
                self._start(fault, ts, "status", out)
            elif value == "inactive":
                inp = self._inputs.get(fault)
                if inp is None or not inp.status:
                    continue
                inp.status = False
                # A DM1 still repeating keeps the fault; a DM1 gone quiet does not.
                if not inp.dm1 or ts - inp.dm1_last > self.dm1_stale_after_s:
                    inp.dm1 = False
                    self._close(fault, ts, "status", out)
            # "error" and "not_available" say nothing about the fault.
        return out

    def on_heartbeat(self, ts: float, value: int | None) -> list[Change]:
        """The heartbeat must alternate; the same value N times in a row is a stuck monitor."""
        out: list[Change] = []
        if value is None:
            return out
        if value == self._heartbeat:
            self._heartbeat_repeats += 1
        else:
            self._heartbeat = value
            self._heartbeat_repeats = 1
            if HEARTBEAT_STUCK in self.open:
                self._close(HEARTBEAT_STUCK, ts, "heartbeat", out)
        if self._heartbeat_repeats >= self.heartbeat_stuck_after:
            if HEARTBEAT_STUCK not in self.open:
                self._start(HEARTBEAT_STUCK, ts, "monitor", out)
            else:
                self.open[HEARTBEAT_STUCK].last_seen_at = ts
        return out

    def end_all(self, ts: float, by: str) -> list[Change]:
        """Close every open episode at `ts` (the unit is gone: another node took its address)."""
        out: list[Change] = []
        for fault in list(self.open):
            self._close(fault, ts, by, out)
        self._inputs.clear()
        return out

    def tick(self, now: float, bus: BusActivity | None = None) -> list[Change]:
        """Clock advance: silent units go offline, or parked when their whole bus fell silent
        with them; DM1 faults no longer repeated go stale.

        With `bus` (the unit's bus, every node's frames), a silent unit is offline only when
        the bus carried traffic for the offline window after the unit's last frame; a unit
        whose bus fell silent before that is parked (from the bus's silence on, not after the
        offline window). Without it, silence alone makes a unit offline."""
        out: list[Change] = []
        last = self._last_frame
        if last is not None and not self._awaiting_bus and OFFLINE not in self.open:
            since = last if self._watch_from is None else max(last, self._watch_from)
            window = self.offline_after_s
            if bus is None:
                if now - since > window:
                    self._start(OFFLINE, last, "monitor", out)
            elif self.parked_since is not None:
                # Parked until heard; once the bus carries traffic again (ignition on), the
                # unit has the offline window from then to be heard.
                if bus.active_since > self.parked_since:
                    since = max(since, bus.active_since)
                    if bus.heard - since >= window and now - since > window:
                        self.parked_since = None
                        self._start(OFFLINE, last, "monitor", out)
            elif bus.heard - since >= window:
                if now - since > window:
                    self._start(OFFLINE, last, "monitor", out)
            elif now - max(bus.heard, since) > bus.silent_after_s:
                self.parked_since = max(last, bus.heard)
        for fault, inp in self._inputs.items():
            ep = self.open.get(fault)
            if (
                ep is not None
                and ep.state == ACTIVE
                and inp.dm1
                and not inp.status
                and now - inp.dm1_last > self.dm1_stale_after_s
            ):
                ep.state = STALE
                out.append((events.FAULT_STALE, ep))
        return out
