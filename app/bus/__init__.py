"""bus: python-can I/O: live buses, logs, socketcand; every frame in and out passes here.

`reader.py` (`BusReader`: a bus's frames into asyncio, bounded, reconnecting), `writer.py`
(`BusWriter`: the one transmit path per bus, the stall check, the address claim), `replay.py`
and `log_filters.py` (logs as frame sources), `candump.py` (a candump reader that survives
broken lines), `mf4.py` (asammdf loaded when an MF4 log is, not at start),
`socketcand_server.py`, `config.py` (`BusConfig`). Decoding is `eqgw.protocol`'s.
"""
