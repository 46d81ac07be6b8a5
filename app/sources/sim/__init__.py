"""A simulated sensor head with exact ground truth (ray-cast in numpy)."""
