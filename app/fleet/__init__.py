"""fleet: vehicles, their buses and their diagnosis"""
