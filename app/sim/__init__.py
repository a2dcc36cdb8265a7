"""sim: the simulated fleet: electrical model, equalizer behaviour, scenarios; `eqgw simulate`."""
