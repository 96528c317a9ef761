"""The deadlock `hte_jax.cpu_pool` prevents, on purpose: batched Cholesky factorisations (MJX's Newton solver
factors each robot's 24 x 24 matrix every step) split over the CPU devices of one process.

    XLA_FLAGS=--xla_force_host_platform_device_count=2 python -m tests.cpu_pool_script [--bare] [--loops N]

Prints "finished N" after N runs of the program. Without `--bare` it imports hte_jax first (which sizes
XLA's CPU pool); with it, jax starts with the pool at its default size (NPROC as the environment has it).
"""

from __future__ import annotations

import argparse

ROWS_PER_DEVICE = 96  # batch x n^3 / 3 past jaxlib's threshold for splitting a batched factorisation
SIZE = 24  # the hexapod's degrees of freedom: MJX's Newton matrix is SIZE x SIZE


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--bare", action="store_true", help="do not import hte_jax before jax starts")
    parser.add_argument("--loops", type=int, default=1)
    args = parser.parse_args()
    if not args.bare:
        import hte_jax  # noqa: F401

    import jax
    import jax.numpy as jnp
    from jax.sharding import Mesh, NamedSharding, PartitionSpec

    def solver_steps(matrix):
        def step(_, x):
            return x + 1e-3 * jnp.linalg.cholesky(x @ x.T + SIZE * jnp.eye(SIZE))
        return jax.lax.fori_loop(0, 200, step, matrix).sum()

    program = jax.jit(jax.vmap(solver_steps))
    mesh = Mesh(jax.devices(), ("batch",))
    batch = jax.random.normal(jax.random.key(0), (ROWS_PER_DEVICE * len(jax.devices()), SIZE, SIZE))
    batch = jax.device_put(batch, NamedSharding(mesh, PartitionSpec("batch")))
    for loop in range(args.loops):
        program(batch + loop).block_until_ready()
    print(f"finished {args.loops}", flush=True)


if __name__ == "__main__":
    main()
