"""The one override rule (`hte_jax.config.with_overrides`) on flat and nested configuration dataclasses."""

import dataclasses

import pytest

from hte_jax import config as configuration
from hte_jax.config import config_dict, config_from_dict, inline, settings, with_overrides
from hte_jax.errors import ConfigError, require_int
from hte_jax.flat import training as flat_training
from hte_jax.hbr import training as hbr_training
from hte_jax.hbr.training import PRESETS, LayerSchedule
from hte_jax.online import evaluation
from hte_jax.online.mcts import PlannerConfig


@dataclasses.dataclass(frozen=True)
class Inner:
    count: int = 1
    scale: float = 0.5
    name: str = "a"

    def __post_init__(self):
        require_int("count", self.count)


@dataclasses.dataclass(frozen=True)
class Middle:
    inner: Inner = Inner()
    flag: bool = False


@dataclasses.dataclass(frozen=True)
class Outer:
    middle: Middle = Middle()
    seed: int = 0
    label: str = ""

    def __post_init__(self):
        require_int("seed", self.seed, minimum=0)


@dataclasses.dataclass(frozen=True)
class Flattened:
    inner: Inner = inline(Inner(count=2))
    middle: Middle = Middle()
    seed: int = 0


def test_inlined_settings_read_as_the_parents_own():
    """An `inline` configuration: overridden by its own names or through its field, stored flat, read
    back from the flat or the nested layout, and its checks' messages carry no path."""
    config = with_overrides(Flattened(), {"count": "3", "inner.scale": "2", "middle.inner.count": 4})
    assert config == Flattened(inner=Inner(count=3, scale=2.0), middle=Middle(inner=Inner(count=4)))
    stored = config_dict(config)
    assert stored == {"count": 3, "scale": 2.0, "name": "a", "middle": {"inner": {"count": 4, "scale": 0.5,
                                                                                   "name": "a"}, "flag": False},
                      "seed": 0}
    assert config_from_dict(Flattened, stored) == config == config_from_dict(Flattened, dataclasses.asdict(config))
    assert config_from_dict(Flattened, {"scale": 2.0}) == Flattened(inner=Inner(count=2, scale=2.0))
    assert config_from_dict(Flattened, {"seed": 1}, base=config) == dataclasses.replace(config, seed=1)
    assert list(settings(Flattened)) == ["count", "scale", "name", "middle.inner.count", "middle.inner.scale",
                                         "middle.inner.name", "middle.flag", "seed"]
    with pytest.raises(ConfigError) as error:
        with_overrides(Flattened(), {"count": "0"})
    assert str(error.value) == "count must be an integer >= 1, got 0"
    with pytest.raises(ConfigError) as error:
        config_from_dict(Flattened, {"middle": {"inner": {"count": 0}}})
    assert str(error.value) == "middle.inner.count must be an integer >= 1, got 0"
    for key in ("inner", "middle.count", "inner.inner"):
        with pytest.raises(ConfigError, match=f"^unknown setting '{key}'$"):
            with_overrides(Flattened(), {key: 1})
    with pytest.raises(TypeError):
        config_from_dict(Flattened, {"colour": 1})


def test_every_module_shares_the_one_rule():
    assert hbr_training.with_overrides is configuration.with_overrides
    assert flat_training.with_overrides is configuration.with_overrides
    assert evaluation.with_overrides is configuration.with_overrides


def test_nested_keys_and_type_conversion():
    config = with_overrides(Outer(), {"middle.inner.count": "3", "middle.inner.scale": "2", "seed": 4.0,
                                      "middle.inner.name": "b", "label": 7})
    assert config == Outer(middle=Middle(inner=Inner(count=3, scale=2.0, name="b")), seed=4, label="7")
    assert type(config.middle.inner.scale) is float and type(config.seed) is int
    assert with_overrides(Outer(), {"middle.flag": True}).middle.flag is True
    assert with_overrides(Outer(), {}) == Outer()


def test_the_original_is_unchanged():
    original = Outer()
    with_overrides(original, {"middle.inner.count": "3"})
    assert original == Outer()


@pytest.mark.parametrize("key", ["colour", "middle", "middle.inner", "seed.x", "middle.colour", "middle.inner.count.x",
                                 "colour.count", "", "middle.", ".seed"])
def test_unknown_settings(key):
    with pytest.raises(ConfigError) as error:
        with_overrides(Outer(), {key: 1})
    assert str(error.value) == f"unknown setting {key!r}"


def test_unreadable_values():
    with pytest.raises(ConfigError) as error:
        with_overrides(Outer(), {"middle.inner.count": "many"})
    assert str(error.value) == "setting 'middle.inner.count': cannot read 'many' as int"
    with pytest.raises(ConfigError) as error:
        with_overrides(Outer(), {"seed": None})
    assert str(error.value) == "setting 'seed': cannot read None as int"


def test_every_post_init_check_runs_with_the_inner_path_named():
    with pytest.raises(ConfigError) as error:
        with_overrides(Outer(), {"seed": "-1"})
    assert str(error.value) == "seed must be an integer >= 0, got -1"
    with pytest.raises(ConfigError) as error:
        with_overrides(Outer(), {"middle.inner.count": "0"})
    assert str(error.value) == "middle.inner.count must be an integer >= 1, got 0"


def test_hbr_overrides_as_before():
    gpu = PRESETS["gpu"]
    config = with_overrides(gpu, {"middle.generations": "7", "seed": "3", "contact_threshold": 0.25,
                                  "top.eta_m": "20"})
    assert config == dataclasses.replace(
        gpu, seed=3, contact_threshold=0.25, middle=dataclasses.replace(gpu.middle, generations=7),
        top=dataclasses.replace(gpu.top, eta_m=20.0))
    assert config.to_dict() == {**gpu.to_dict(), "seed": 3, "contact_threshold": 0.25,
                                "middle": {**gpu.to_dict()["middle"], "generations": 7},
                                "top": {**gpu.to_dict()["top"], "eta_m": 20.0}}
    tiny = with_overrides(PRESETS["tiny"], {"bottom.batch_size": "8", "bottom.init_size": "16",
                                            "solver_iterations": "6"})
    assert tiny.bottom == LayerSchedule(batch_size=8, init_size=16, generations=2, block_size=1, mutation_rate=0.17,
                                        capacity=256)
    assert tiny.solver.solver_iterations == 6 and tiny.middle is PRESETS["tiny"].middle


@pytest.mark.parametrize("overrides, message", [
    ({"middle.colour": 1}, "unknown setting 'middle.colour'"),
    ({"middle": 1}, "unknown setting 'middle'"),
    ({"seed.x": 1}, "unknown setting 'seed.x'"),
    ({"middle.generations": "x"}, "setting 'middle.generations': cannot read 'x' as int"),
    ({"middle.mutation_rate": "2"}, "middle.mutation_rate must be a finite number in [0.0, 1.0], got 2.0"),
    ({"bottom.generations": "-1", "seed": "-1"}, "bottom.generations must be an integer >= 0, got -1"),
    ({"bottom_fitness": "energy"}, "bottom_fitness must be one of ('commands', 'genes'), got 'energy'"),
])
def test_hbr_errors_as_before(overrides, message):
    with pytest.raises(ConfigError) as error:
        with_overrides(PRESETS["gpu"], overrides)
    assert str(error.value) == message


def test_flat_and_evaluation_overrides_as_before():
    flat = with_overrides(flat_training.preset("cpu", "2d"), {"generations": "3", "mutation_rate": "0.2", "seed": 5})
    assert flat == flat_training.FlatConfig(variant="2d", batch_size=256, init_size=512, generations=3, block_size=4,
                                            mutation_rate=0.2, seed=5)
    with pytest.raises(ConfigError, match=r"^unknown setting 'speed'$"):
        with_overrides(flat_training.preset("cpu", "2d"), {"speed": 1})
    with pytest.raises(ConfigError, match=r"^unknown setting 'variant.x'$"):
        with_overrides(flat_training.preset("cpu", "2d"), {"variant.x": 1})
    config = with_overrides(evaluation.preset("cpu"), {"iterations": "5", "roots": 3, "exploration": "2",
                                                       "variants": "hte,rte"})
    assert config == evaluation.EvalConfig(planner=PlannerConfig(iterations=5, roots=3, exploration=2.0), variants="hte,rte")
    with pytest.raises(ConfigError, match=r"^setting 'seed': cannot read '1.5' as int$"):
        with_overrides(evaluation.preset("cpu"), {"seed": "1.5"})


# Configurations as stored before the nested ones (`to_dict` of then: every setting flat), changed
# from the presets in a few places.
OLD_EVAL = {"variants": "hte", "damages": "all", "replicates": 30, "repertoire": "", "repertoire_dir": "",
            "damage_model": "raised", "max_actions": 80, "iterations": 50, "roots": 4, "candidates": 100,
            "exploration": 100.0, "widening": 0.5, "gamma": 0.9, "depth": 20, "optimism": 0.0, "composition": "planned",
            "spare": "", "pattern_ends": "", "seed": 0, "solver_iterations": 2, "ls_iterations": 4,
            "solver_tolerance": 1e-08, "reflex_tilt": 0.3}
OLD_LAYER = {"batch_size": 16, "init_size": 32, "generations": 2, "block_size": 1, "mutation_rate": 0.17, "eta_m": 10.0,
             "capacity": 256, "selection": "uniform", "density_bins": 16, "density_dims": 3, "frontier_fraction": 0.5,
             "frontier_angle_bins": 16, "frontier_level_bins": 16}
OLD_HBR = {"bottom": OLD_LAYER, "middle": {**OLD_LAYER, "mutation_rate": 0.11},
           "top": {**OLD_LAYER, "mutation_rate": 0.14, "capacity": 1, "density_bins": 8},
           "seed": 0, "middle_samples": 2, "contact_threshold": 0.3, "contact_purity": 0.0, "bottom_l": 0.01,
           "middle_l": 0.05, "top_bins": 100, "bottom_fitness": "commands", "solver_iterations": 6, "ls_iterations": 4,
           "solver_tolerance": 1e-08, "step_starts": 2}
HBR_ADDED = {"step_chunk": 8192}  # HBR settings added since, at their defaults
# OLD_HBR as stored today: the layers without the parent selections' settings (levers E, F left)
HBR_NOW = {**OLD_HBR, **{layer: {k: v for k, v in OLD_HBR[layer].items() if k not in hbr_training.RETIRED_SELECTION}
                         for layer in ("bottom", "middle", "top")}}
OLD_FLAT = {"variant": "8d", "batch_size": 16, "init_size": 32, "generations": 2, "block_size": 1, "mutation_rate": 0.14,
            "eta_m": 10.0, "seed": 0, "bins": 20, "contact_threshold": 0.3, "solver_iterations": 3, "ls_iterations": 4,
            "solver_tolerance": 1e-08}


def test_configurations_stored_flat_read_as_the_nested_ones():
    """A configuration stored before the nesting (flat) reads as the same nested configuration as the
    nested layout does, and is stored again as it was (with the settings added since: the planner's two
    rewards, the tilt reflex's release and rate, the maze, the seeds to run, MJX's implementation)."""
    evaluation_config = with_overrides(evaluation.preset("gpu"), {"planner.iterations": 50, "planner.roots": 4,
                                                                  "solver.solver_iterations": 2, "reflex_tilt": 0.3})
    hbr = with_overrides(PRESETS["tiny"], {"solver_iterations": 6})
    flat = with_overrides(flat_training.preset("tiny", "8d"), {"solver_iterations": 3})
    for cls, old, config in ((evaluation.EvalConfig, OLD_EVAL, evaluation_config), (hbr_training.HBRConfig, OLD_HBR, hbr),
                             (flat_training.FlatConfig, OLD_FLAT, flat)):
        assert cls.from_dict(old) == config == cls.from_dict(dataclasses.asdict(config))
        assert cls.from_dict(config.to_dict()) == config
        added = {evaluation.EvalConfig: {"collision_reward": -1000.0, "goal_reward": 100.0, "reflex_release": 0.0,
                                         "maze": "", "seeds": ""},
                 hbr_training.HBRConfig: HBR_ADDED}.get(cls, {})  # settings added since, at their defaults
        retired = evaluation.RETIRED if cls is evaluation.EvalConfig else {}  # settings of levers that left
        now = HBR_NOW if cls is hbr_training.HBRConfig else old
        assert config.to_dict() == {**{k: v for k, v in now.items() if k not in retired}, **added, "impl": "jax"}
    assert hbr_training.normalised_config(OLD_HBR) == {**HBR_NOW, **HBR_ADDED, "impl": "jax"}
    with pytest.raises(ConfigError, match="top.selection 'density' left hte-jax"):
        hbr_training.HBRConfig.from_dict({**OLD_HBR, "top": {**OLD_HBR["top"], "selection": "density"}})
    assert flat_training.normalised_config(OLD_FLAT) == {**OLD_FLAT, "impl": "jax"}
    with pytest.raises(ConfigError, match="left hte-jax"):
        evaluation.EvalConfig.from_dict({**OLD_EVAL, "optimism": 1.0})
    assert evaluation.EvalConfig.from_dict({**OLD_EVAL, "reflex_rate": 0.0}) == evaluation_config  # the gate, off
    with pytest.raises(ConfigError, match="'reflex_rate' belongs to a lever that left hte-jax"):
        evaluation.EvalConfig.from_dict({**OLD_EVAL, "reflex_rate": 0.5})
