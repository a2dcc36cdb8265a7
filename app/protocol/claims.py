"""Who holds which J1939 source address on a bus, from the Address Claimed frames (PGN 60928)
seen on it: pure state, no I/O.

A node is its NAME: when another NAME takes an address, the frames from that address are the
new node's, not the old one's. J1939-81 decides a contention by the NAME: the lower one wins.

- A claim for a free address (or the first seen for it) makes its NAME the owner.
- A claim with a lower NAME than the owner's takes the address at once (the owner must yield).
- A claim with a higher NAME is a challenge the owner defends by claiming again; if the owner
  does not within `defend_s` (J1939-81: the contender waits 250 ms), it is gone and the
  challenger holds the address (a unit replaced while the old one is off the bus).
- "Cannot claim" (a claim from the null address 254) frees whatever address its NAME held, as
  does a claim of the same NAME for another address.

`observe` and `tick` return the `OwnerChange`s they decide: an address that passes from one
NAME to another, or is first claimed.
"""

from __future__ import annotations

from dataclasses import dataclass

PGN_ADDRESS_CLAIMED = 0xEE00
NULL_ADDRESS = 0xFE
DEFEND_S = 0.5  # J1939-81's 250 ms, with room for a loaded bus or log timestamps


@dataclass(frozen=True, slots=True)
class OwnerChange:
    """Address `address` passed from NAME `previous` (None: nobody known) to `name` at `ts`."""

    ts: float
    address: int
    previous: int | None
    name: int


def is_address_claim(can_id: int) -> bool:
    """Whether a 29-bit identifier is an Address Claimed frame (PF 0xEE)."""
    return (can_id >> 16) & 0xFF == PGN_ADDRESS_CLAIMED >> 8


class ClaimTracker:
    """The owners of the addresses of one bus, as its address claims say."""

    def __init__(self, defend_s: float = DEFEND_S) -> None:
        self.defend_s = defend_s
        self.owners: dict[int, int] = {}  # address -> NAME
        self._address_of: dict[int, int] = {}  # NAME -> address
        self._challenges: dict[int, tuple[int, float]] = {}  # address -> (NAME, since)
        self._released: dict[int, int] = {}  # address -> the NAME that gave it up

    def owner(self, address: int) -> int | None:
        """The NAME holding `address`, if known."""
        return self.owners.get(address)

    def observe(self, ts: float, can_id: int, data: bytes) -> list[OwnerChange]:
        """An Address Claimed frame seen at `ts` (others are ignored)."""
        if not is_address_claim(can_id) or len(data) < 8:
            return []
        changes = self.tick(ts)
        address = can_id & 0xFF
        name = int.from_bytes(data[:8], "little")
        if address == NULL_ADDRESS:
            self._release(name)
            return changes
        if address > 253:
            return changes
        owner = self.owners.get(address)
        if owner is None and self._released.get(address) == name:
            # The node that gave the address up claims it again: the same node, no change.
            del self._released[address]
            self.owners[address] = name
            self._address_of[name] = address
            return changes
        if owner == name:
            self._challenges.pop(address, None)  # claimed again: defended
            return changes
        if owner is None or name < owner:
            changes.append(self._take(ts, address, name, owner))
        elif address not in self._challenges:
            self._challenges[address] = (name, ts)
        return changes

    def tick(self, now: float) -> list[OwnerChange]:
        """Challenges the owner did not defend in time: their challengers hold the address."""
        changes: list[OwnerChange] = []
        for address, (name, since) in list(self._challenges.items()):
            if now - since > self.defend_s:
                changes.append(self._take(since, address, name, self.owners.get(address)))
        return changes

    def _release(self, name: int) -> None:
        address = self._address_of.pop(name, None)
        if address is not None and self.owners.get(address) == name:
            del self.owners[address]
            self._released[address] = name

    def _take(self, ts: float, address: int, name: int, previous: int | None) -> OwnerChange:
        self._challenges.pop(address, None)
        if previous is None:
            previous = self._released.pop(address, None)
        else:
            self._address_of.pop(previous, None)
        self._release(name)  # a NAME holds one address
        self.owners[address] = name
        self._address_of[name] = address
        return OwnerChange(ts, address, previous, name)
