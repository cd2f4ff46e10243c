"""dear_jax: DEAR and its baselines (DrQ-v2, SEAR, TED) as pure JAX functions.

`dear_jax.losses` is importable on its own into any JAX agent.
"""

__version__ = "0.1.0"
