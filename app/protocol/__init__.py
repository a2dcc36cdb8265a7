"""The equalizer protocol: pure J1939 decode and encode, no I/O."""
