"""eqgw api layer."""
