"""eqgw: fleet gateway for Vanner VANN-Guard battery equalizers."""
