"""Edge forwarding: a vehicle's frames buffered locally and uploaded to the central service."""
