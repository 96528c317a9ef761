"""A QD problem in one place (what an elite is, where it is kept, how it is evaluated), read by loops and files."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

import jax.numpy as jnp
import numpy as np

from hte_jax.errors import ConfigError, require_int, require_number

# evaluate(key, genotypes (B, G)) -> Evaluation with B rows, jittable (+ a condition: `BatchedMapElites`).
EvaluateFn = Callable[..., Any]


def container_metadata(container) -> dict:
    """The container as JSON-able data: its class name and its fields (what checkpoints compare)."""
    return {"kind": type(container).__name__, **dataclasses.asdict(container)}


@dataclasses.dataclass(frozen=True, eq=False)
class TaskSpec:
    """One QD problem (static; the evaluation is compared by identity)."""

    name: str  # label of its repertoire files
    genotype_dim: int  # G genes, each in [0, 1]
    container: Any  # `Grid` or `Archive`
    evaluate: EvaluateFn | None = None  # evaluate(key, genotypes (B, G)) -> Evaluation; None: `with_evaluate` adds one
    extras: dict = dataclasses.field(default_factory=dict)  # {name: (shape without rows, dtype)}, e.g. ((), "int32")
    qd_offset: float | None = None  # the QD score's fitness lower bound; None: the config's

    def __post_init__(self):
        if not isinstance(self.name, str) or not self.name:
            raise ConfigError(f"task name must be a non-empty string, got {self.name!r}")
        require_int("genotype_dim", self.genotype_dim)
        for attribute in ("capacity", "descriptor_dim", "low", "high", "empty", "add"):
            if not hasattr(self.container, attribute):
                raise ConfigError(f"task {self.name!r}: the container has no {attribute!r} (a Grid or an Archive is needed)")
        if self.qd_offset is not None:
            require_number("qd_offset", self.qd_offset)
        extras = {}
        for key, layout in dict(self.extras).items():
            try:
                shape, dtype = layout
                shape = tuple(int(n) for n in shape)
                dtype = np.dtype(dtype)
            except (TypeError, ValueError):
                raise ConfigError(f"task {self.name!r}: extra {key!r} must be (shape, dtype), got {layout!r}") from None
            if any(n < 0 for n in shape) or dtype.kind not in "biuf":
                raise ConfigError(f"task {self.name!r}: extra {key!r} needs a shape of sizes >= 0 and a numeric dtype")
            extras[str(key)] = (shape, dtype)
        object.__setattr__(self, "extras", extras)

    @property
    def capacity(self) -> int:
        return self.container.capacity

    @property
    def descriptor_dim(self) -> int:
        return self.container.descriptor_dim

    def extras_example(self) -> dict:
        """{name: zeros of the extra's shape and dtype}: the example pytree `MapElites.extras` takes."""
        return {name: jnp.zeros(shape, dtype) for name, (shape, dtype) in self.extras.items()}

    def empty(self):
        return self.container.empty(self.genotype_dim, self.extras_example())

    def with_evaluate(self, evaluate: EvaluateFn) -> TaskSpec:
        """The same spec with an evaluation (for specs whose evaluation needs objects known only at run time)."""
        return dataclasses.replace(self, evaluate=evaluate)

    def metadata(self) -> dict:
        """The spec as JSON-able data, what repertoire files store and compare."""
        return {"name": self.name, "genotype_dim": self.genotype_dim, "container": container_metadata(self.container),
                "extras": {name: [list(shape), dtype.name] for name, (shape, dtype) in sorted(self.extras.items())}}
