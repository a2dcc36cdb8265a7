"""ingest: frames to live state, faults, events and batched database writes.

`pipeline.py` (`IngestPipeline`: decode, per-unit live state, fault tracking), `state.py`
(live state), `faults.py` (`FaultTracker`: fault episodes), `writer.py` (`BatchedWriter`: the one
thread that writes the time series, one transaction per batch), `journal.py` (rows held while
the database is away), `hub.py` and `events.py` (`EventHub`: bounded fan-out of events),
`service.py` (`IngestService`: readers, pipeline, writer, monitors, retention), `replay.py`
and `cli.py` (`eqgw replay`, `eqgw db`). The SQL of a write is `eqgw.store.writes`'.
"""
