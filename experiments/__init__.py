"""Command-line entry points (`python -m experiments.<name>`), thin layers over `hte_jax`."""
