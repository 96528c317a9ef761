"""The adaptation variants, one table entry each: the repertoire an episode plans with and, for the
HBR, the pattern rule (`docs/design.md`, The variant table; `add_variant` adds one).
"""

from __future__ import annotations

import dataclasses

from hte_jax.errors import ConfigError
from hte_jax.online.rules import AnyPattern, GpUcb, Oracle, PatternRule, RandomPattern, SensedLegs

REPERTOIRES = ("hbr", "2d", "8d", "aprol")  # the HBR, or a shipped flat repertoire (APROL: its 21)


@dataclasses.dataclass(frozen=True)
class Variant:
    """One adaptation variant. name: what `maze_eval --variant` calls it. rule: the `rules.PatternRule` of
    each step's pattern (`AnyPattern` for flat repertoires). repertoire: one of `REPERTOIRES`. summary: one
    line for the docs and `--help`."""

    name: str
    rule: PatternRule = AnyPattern()
    repertoire: str = "hbr"
    summary: str = ""

    @property
    def hierarchical(self) -> bool:
        return self.repertoire == "hbr"

    def check_skills(self, skills) -> None:
        """ConfigError unless this variant can run on `skills`: a rule other than RTE's needs an HBR."""
        if not skills.hierarchical and self.rule != AnyPattern():
            raise ConfigError(f"variant {self.name!r} needs an HBR (a flat repertoire has no secondary descriptor)")

    @property
    def spares(self) -> bool:
        """Whether the variant ever runs steps from spare sets (`hbr.spare`)."""
        return bool(getattr(self.rule, "spare", False))


VARIANTS: dict[str, Variant] = {}


def add_variant(variant: Variant) -> Variant:
    """Register a variant (names are unique)."""
    if variant.name in VARIANTS:
        raise ConfigError(f"variant {variant.name!r} is already defined")
    if not isinstance(variant.rule, PatternRule):
        raise ConfigError(f"variant {variant.name!r}: its rule must be a rules.PatternRule, got {variant.rule!r}")
    if variant.repertoire not in REPERTOIRES:
        raise ConfigError(f"variant {variant.name!r}: repertoire {variant.repertoire!r} is not one of "
                          f"{', '.join(REPERTOIRES)}")
    if not variant.hierarchical and variant.rule != AnyPattern():
        raise ConfigError(f"variant {variant.name!r}: a flat repertoire has no contact patterns to choose")
    VARIANTS[variant.name] = variant
    return variant


for _variant in (
    Variant("hte", GpUcb(), summary="the paper's HTE: GP-UCB over 36 contact patterns"),
    Variant("perfect-hte", Oracle(), summary="the pattern of the true damage (an upper bound)"),
    Variant("random-hte", RandomPattern(), summary="a uniform random pattern each step (a lower bound)"),
    Variant("rte", AnyPattern(), summary="RTE on the HBR: the nearest middle elite of any pattern"),
    Variant("hte-spare", SensedLegs(spare=True),
            summary="ours: lift the legs sensed off the floor or not following their joint commands, "
                    "keeping those off the floor really off it"),
    Variant("perfect-spare", Oracle(spare=True),
            summary="the true damage's legs kept really off the floor (an upper bound for hte-spare)"),
    Variant("rte-spare", AnyPattern(spare=True),
            summary="RTE on the HBR's and the spare archive's elites together, nothing sensed "
                    "(an ablation of hte-spare)"),
    Variant("hte-sense", SensedLegs(),
            summary="hte-spare's leg sensing on the HBR alone, without the spare sets (an ablation of hte-spare)"),
    Variant("2d-rte", repertoire="2d", summary="RTE on the flat x-y repertoire"),
    Variant("8d-rte", repertoire="8d", summary="RTE on the flat 8-D repertoire"),
    Variant("aprol", repertoire="aprol", summary="APROL's choice among 21 damage repertoires"),
):
    add_variant(_variant)


def variant(name: str) -> Variant:
    """The variant called `name` (clear error otherwise)."""
    if name not in VARIANTS:
        raise ConfigError(f"unknown variant {name!r}; choose from {', '.join(VARIANTS)}")
    return VARIANTS[name]


def batch_rules(names: list[str]) -> tuple[tuple[PatternRule, ...], list[int]]:
    """The distinct rules of the variants `names` (one per episode) in order of use, and each one's index."""
    rules = list(dict.fromkeys(variant(name).rule for name in names))
    return tuple(rules), [rules.index(variant(name).rule) for name in names]
