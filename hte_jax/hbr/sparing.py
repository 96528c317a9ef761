"""Sparing sets: the middle elites that really leave a set of legs alone.

A contact pattern of the middle layer sets a leg's bit to 0 when its foot is down for less than
the layer's threshold of the second (the paper's 30 %): a "lifted" leg may still carry the robot
for a quarter of every step, and a damage that takes the leg away spoils those steps. The
sparing set of a pattern p holds every middle elite whose stored contact fraction is below a
strict threshold (5 %) on each leg p lifts, whatever the other legs do. Planning a skill's steps
among them (`composition.plan_step` on `sparing_table`) executes the skill without the lifted legs.

Elites may come from the HBR's own middle layer and from a second middle archive, trained on the
same bottom layer at the strict threshold (`experiments.train_spare`), appended after the HBR's
own slots (`with_spare`): the HBR's own lookups (RTE's nearest elite, the patterns of the paper's
HTE, training, modulation) never see them, since they are not `filled` in its middle layer.
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from hte_jax.hbr.composition import PatternTable, StepModel, descriptor_steps, measure_steps
from hte_jax.hbr.execution import ANY_PATTERN, HBR
from hte_jax.hbr.middle import NUM_PATTERNS, PRIMARY, elite_controllers, pattern_code
from hte_jax.hbr.store import SPARE_FILE, bottom_fingerprint, save_spare
from hte_jax.hbr.training import HBRConfig, layer_algorithms, normalised_config
from hte_jax.qd import io
from hte_jax.qd.loop import resume, run
from hte_jax.qd.repertoire import Repertoire
from hte_jax.sim.mjx_import import require_impl
from hte_jax.sim.robot import NUM_LEGS, load_robot
from hte_jax.sim.rollout import standing_state

STRICT_CONTACT = 0.05  # a leg counts as lifted by a step that has its foot down less than this share
SPARE_L = 0.035  # the spare archive's distance threshold (the HBR's middle layer: 0.05)
SPARE_STREAM = 7  # folded into the seed's key: the spare archive's draws differ from the HBR's layers'


def lifted_legs(pattern: np.ndarray) -> np.ndarray:
    """(...,) pattern codes (leg 0 = most significant bit, 1 = down) -> (..., 6) bool, legs lifted."""
    bits = (np.asarray(pattern)[..., None] >> (NUM_LEGS - 1 - np.arange(NUM_LEGS))) & 1
    return bits == 0


def sparing_members(contact_fraction: np.ndarray, present: np.ndarray, strict: float = STRICT_CONTACT) -> np.ndarray:
    """(Cm, 6) stored contact fractions and (Cm,) bool usable slots -> (64, Cm) bool: elite e is in
    the sparing set of pattern p when its contact is below `strict` on every leg p lifts."""
    off = np.asarray(contact_fraction) < strict  # (Cm, 6)
    lifted = lifted_legs(np.arange(NUM_PATTERNS))  # (64, 6)
    return np.asarray(present)[None, :] & np.all(off[None, :, :] | ~lifted[:, None, :], axis=-1)


def sparing_table(hbr: HBR, strict: float = STRICT_CONTACT) -> PatternTable:
    """The sparing sets of every pattern as a planning table (host-side: widths are static): rows
    are patterns, members every usable middle elite (the HBR's own and any appended by `with_spare`);
    the row of the pattern that lifts no leg holds that pattern's own elites."""
    present = np.asarray(hbr.middle_patterns) >= 0
    if hbr.spare_count:
        present = present | (np.arange(present.size) >= present.size - hbr.spare_count)
    members = sparing_members(np.asarray(hbr.middle.extras["contact_fraction"]), present, strict)
    # a pattern that lifts no leg spares nothing: its set is its own elites, not the whole layer
    # (which would also make every row of the table as wide as the layer)
    members[NUM_PATTERNS - 1] = np.asarray(hbr.middle_patterns) == NUM_PATTERNS - 1
    width = max(int(members.sum(axis=1).max()), 1)
    index = np.full((NUM_PATTERNS, width), -1, np.int32)
    for p in range(NUM_PATTERNS):
        rows = np.flatnonzero(members[p])
        index[p, : rows.size] = rows
    model = hbr.step_model if hbr.step_model is not None else descriptor_steps(hbr.middle.descriptors)
    rows = jnp.asarray(np.maximum(index, 0))
    usable = jnp.asarray(index >= 0) & jnp.isfinite(jnp.asarray(model.spread)[rows])
    return PatternTable(index=jnp.asarray(index), steps=jnp.asarray(model.steps)[rows],
                       penalty=jnp.where(usable, 0.0, jnp.inf))


def with_spare(hbr: HBR, spare: Repertoire, spare_params: jnp.ndarray, spare_steps: StepModel | None) -> HBR:
    """The HBR with a second middle archive's elites appended after its own slots.

    spare: the archive (genotypes (Cs, 18) over the HBR's own bottom layer, descriptors (Cs, 9), extras
    with "contact_fraction" (Cs, 6)); spare_params: (Cs, 36) their controllers; spare_steps: their
    measured steps, or None (the stored descriptors). Only the filled elites are appended; their
    contact bits are re-computed at the HBR's threshold, so every learning rule reads them alike.
    """
    filled = np.asarray(spare.filled)
    rows = np.flatnonzero(filled)
    fraction = np.asarray(spare.extras["contact_fraction"])[rows]
    descriptors = np.asarray(spare.descriptors)[rows].copy()
    descriptors[:, PRIMARY:] = fraction > hbr.middle_task.contact_threshold
    main = hbr.middle
    extras = {name: jnp.concatenate([value, jnp.asarray(np.asarray(spare.extras[name])[rows])])
              for name, value in main.extras.items()}
    middle = Repertoire(
        genotypes=jnp.concatenate([main.genotypes, jnp.asarray(np.asarray(spare.genotypes)[rows])]),
        descriptors=jnp.concatenate([main.descriptors, jnp.asarray(descriptors)]),
        fitnesses=jnp.concatenate([main.fitnesses, jnp.asarray(np.asarray(spare.fitnesses)[rows])]),
        filled=jnp.concatenate([main.filled, jnp.zeros(rows.size, bool)]),
        extras=extras,
    )
    own = hbr.step_model if hbr.step_model is not None else descriptor_steps(main.descriptors)
    added = spare_steps if spare_steps is not None else descriptor_steps(spare.descriptors)
    steps = StepModel(steps=jnp.concatenate([own.steps, jnp.asarray(np.asarray(added.steps)[rows])]),
                      spread=jnp.concatenate([own.spread, jnp.asarray(np.asarray(added.spread)[rows])]))
    params = jnp.concatenate([hbr.middle_params, jnp.asarray(np.asarray(spare_params)[rows])])
    patterns = jnp.concatenate([hbr.middle_patterns, jnp.full(rows.size, ANY_PATTERN, jnp.int32)])
    return hbr.replace(middle=middle, middle_params=params, middle_patterns=patterns, step_model=steps,
                       spare_count=int(rows.size))


def _normalised_spare_config(stored: dict) -> dict:
    """A spare run's stored configuration with its HBR settings read through today's HBRConfig
    (settings added since: the values such runs ran with, `hbr.training.normalised_config`)."""
    if "hbr_config" not in stored:
        return stored
    return {**stored, "hbr_config": normalised_config(stored["hbr_config"])}


def train_spare(hbr: HBR, base: HBRConfig, out_dir: str | Path, *, threshold: float = STRICT_CONTACT,
                l: float = SPARE_L, resume_run: bool = False, progress: bool = True) -> dict:
    """Train a second middle archive for `hbr`'s sparing sets: its middle layer's task and budget
    (`base.middle`, samples, solver) at contact threshold `threshold` and distance threshold `l`, on
    the HBR's own bottom layer; then measure its steps (`base.step_starts`). Writes the run folder
    (config.json, middle/ checkpoint and metrics, spare.npz, summary.json; a killed run resumes)
    and returns the summary."""
    config = dataclasses.replace(base, contact_threshold=threshold, middle_l=l, contact_purity=0.0)
    out = Path(out_dir)
    require_impl(config.robot.impl)  # before the run folder is made: a missing extra writes nothing
    io.prepare_run_dir(out, {"hbr_config": config.to_dict(), "bottom": bottom_fingerprint(hbr)}, resume_run,
                       normalise=_normalised_spare_config)
    robot = load_robot(config.robot)
    start = standing_state(robot)
    algo = layer_algorithms(config, robot, start, {"bottom": hbr.bottom})["middle"]()
    key, step_key = jax.random.split(jax.random.fold_in(jax.random.PRNGKey(config.seed), SPARE_STREAM))
    checkpoint = out / "middle" / "checkpoint.npz"
    began = time.perf_counter()
    state = resume(algo, checkpoint) if checkpoint.exists() else algo.init(key)
    state = run(algo, state, config.middle.generations, block_size=config.middle.block_size,
                log_path=out / "middle" / "metrics.csv", checkpoint_path=checkpoint, progress=progress,
                description="spare")
    if not checkpoint.exists():  # no block ran (generations = 0)
        io.save_checkpoint(checkpoint, state, algo.checkpoint_metadata())
    trained = time.perf_counter() - began
    spare = state.repertoire
    steps = None
    if config.step_starts:
        params = elite_controllers(hbr.bottom, spare.genotypes, spare.filled)
        steps = jax.device_get(measure_steps(robot, params, spare.filled, config.middle_task, start, step_key,
                                             starts=config.step_starts))
    filled = np.asarray(spare.filled)
    fraction = np.asarray(spare.extras["contact_fraction"])[filled]
    own = np.asarray(hbr.middle.extras["contact_fraction"])[np.asarray(hbr.middle.filled)]
    summary = {
        "threshold": threshold, "l": l, "evaluations": algo.evaluations(state), "elites": int(filled.sum()),
        "patterns": int(np.unique(np.asarray(pattern_code(spare.descriptors[:, PRIMARY:]))[filled]).size),
        "lifting_each_leg": {"spare": (fraction < threshold).sum(axis=0).tolist(),
                             "hbr": (own < threshold).sum(axis=0).tolist()},
        "wall_time_s": {"training": trained, "steps": time.perf_counter() - began - trained},
        "devices": [str(d) for d in jax.devices()],
    }
    save_spare(out / SPARE_FILE, hbr, spare, steps, l, metadata={"training": summary})
    io.write_json(out / "summary.json", summary)
    return summary
