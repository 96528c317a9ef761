"""The device flags every training and evaluation CLI shares: `--devices N` (the first N visible
devices; default all) and `--distributed` (a multi-host run through `jax.distributed`)."""

from __future__ import annotations

import argparse

import jax
from jax.sharding import Mesh

from hte_jax import sharding
from hte_jax.errors import ConfigError


def add_device_flags(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--devices", type=int, default=None, metavar="N",
                        help="spread every batch over the first N visible devices (default: all)")
    parser.add_argument("--distributed", action="store_true",
                        help="multi-host run: jax.distributed.initialize() first (SLURM / Open MPI / cloud "
                             "TPU settings are read from the environment); only process 0 writes files")


def device_mesh(args: argparse.Namespace) -> Mesh:
    """The mesh the flags ask for (call it before anything else touches jax's devices); ConfigError
    on a device count out of range or a failed `jax.distributed.initialize()`."""
    if args.distributed:
        try:
            jax.distributed.initialize()
        except (RuntimeError, ValueError) as error:
            first = str(error).strip().splitlines()[0] if str(error).strip() else type(error).__name__
            raise ConfigError(f"--distributed: jax.distributed.initialize() failed: {first}") from None
    return sharding.batch_mesh(sharding.check_device_count(args.devices))


def is_writer() -> bool:
    """Whether this process writes files (process 0 of a multi-host run, or the only one)."""
    return jax.process_index() == 0
