"""Independent Monte Carlo references (plane and 3-D slab) used as the accuracy contract."""
