"""The scene: the medium, the grid and the illumination."""
