"""eqgw store layer."""
