import jax

# Tests check convergence and gradients: float64 unless a test asks for float32.
jax.config.update("jax_enable_x64", True)
