"""hte-jax: Hierarchical Trial and Error (Allard et al., GECCO 2022) on JAX + MuJoCo MJX."""

from hte_jax import cpu_pool

cpu_pool.size_pool()  # before jax starts its CPU client (hte_jax/cpu_pool.py)

__version__ = "0.1.0"
