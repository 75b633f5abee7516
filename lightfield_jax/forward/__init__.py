"""The forward model: shared kernels, the renderers' base class (bounce loop, refinement,
tail), the plane and the slab as its subclasses, the tail solve, and :func:`render`."""
