"""eqgw bus layer."""
