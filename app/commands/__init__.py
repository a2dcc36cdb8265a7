"""The command queue: validated commands as database rows, delivered to the bus and confirmed."""
