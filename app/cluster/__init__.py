"""Several gateways on one PostgreSQL: bus leases, command routing and event fan-out."""
