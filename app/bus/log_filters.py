"""Log filters that turn python-can's per-read warnings into a periodic summary."""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Iterable

SOCKETCAND_LOGGER = "can.interfaces.socketcand.socketcand"

# python-can's socketcand client warns on every TCP read that ends inside a frame (most reads
# under load) and on every attempt of its 10 s connect loop; neither says anything new after
# the first occurrence.
SOCKETCAND_NOISE: tuple[str, ...] = (
    "Got incomplete message => waiting for more data",
    "Failed to connect to server",
)


class RepeatSummaryFilter(logging.Filter):
    """Lets a repeated log message through at most once per interval, as a counted summary."""

    def __init__(self, prefixes: Iterable[str], interval: float = 60.0) -> None:
        super().__init__()
        self.prefixes = tuple(prefixes)
        self.interval = interval
        # Records come from every bus's reader thread at once.
        self._lock = threading.Lock()
        self._suppressed: dict[str, int] = dict.fromkeys(self.prefixes, 0)
        self._totals: dict[str, int] = dict.fromkeys(self.prefixes, 0)
        self._last_emit: dict[str, float] = {}

    def filter(self, record: logging.LogRecord) -> bool:
        """Pass unrelated records; pass a matching one only when its interval has elapsed."""
        message = record.getMessage()
        prefix = next((p for p in self.prefixes if message.startswith(p)), None)
        if prefix is None:
            return True
        now = time.monotonic()
        with self._lock:
            self._totals[prefix] += 1
            last = self._last_emit.get(prefix)
            if last is not None and now - last < self.interval:
                self._suppressed[prefix] += 1
                return False
            suppressed = self._suppressed[prefix]
            self._suppressed[prefix] = 0
            self._last_emit[prefix] = now
        if last is not None:
            record.msg = (
                f"{message} (and {suppressed} more like it in the last {now - last:.0f} s; "
                f"repeats are summarised once per {self.interval:.0f} s)"
            )
            record.args = ()
        return True

    def counts(self) -> dict[str, int]:
        """Total matching records seen per prefix, emitted or not."""
        with self._lock:
            return dict(self._totals)


def install_socketcand_log_filter(interval: float = 60.0) -> RepeatSummaryFilter:
    """Install (once per process) the summary filter on python-can's socketcand logger."""
    logger = logging.getLogger(SOCKETCAND_LOGGER)
    for existing in logger.filters:
        if isinstance(existing, RepeatSummaryFilter):
            return existing
    summary = RepeatSummaryFilter(SOCKETCAND_NOISE, interval)
    logger.addFilter(summary)
    return summary
