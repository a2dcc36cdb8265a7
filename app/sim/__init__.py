"""eqgw sim layer."""
