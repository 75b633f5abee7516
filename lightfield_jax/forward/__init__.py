"""The forward model: first scattering, bounce transport, the plane and slab renderers, the tail."""
