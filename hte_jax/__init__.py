"""hte-jax: Hierarchical Trial and Error (Allard et al., GECCO 2022) on JAX + MuJoCo MJX."""

__version__ = "0.1.0"
