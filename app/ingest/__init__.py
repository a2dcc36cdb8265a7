"""eqgw ingest layer."""
