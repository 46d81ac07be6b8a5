"""Producers of time-stamped frame sets: simulated, replayed and live sensor heads."""
