"""Does modulation depend on the middle layer's density? Subsample each pattern's elites and re-measure."""
import json, sys, time
import numpy as np, jax.numpy as jnp
from hte_jax.hbr.store import load_hbr
from hte_jax.hbr.composition import planning_table
from hte_jax.hbr.modulation import modulate
from hte_jax.online.secondary import allowed_patterns
from hte_jax.sim.robot import load_robot
from hte_jax.sim.rollout import standing_state

out = {}
robot = load_robot()
for name, path in [("shipped", None), ("5pct", "benchmarks/results/hbr_contact_threshold_0.05_gpu_NVIDIA_H100_2026-11-23/hbr.npz")]:
    hbr, task, _ = load_hbr(path)
    filled = np.asarray(hbr.middle.filled)
    skills = np.flatnonzero(np.asarray(hbr.top.filled))
    skills = np.random.default_rng(1).choice(skills, min(int(sys.argv[1]), skills.size), replace=False)
    skills.sort()
    for keep in (1.0, 0.5, 0.25):
        mask = filled & (np.random.default_rng(0).random(filled.size) < keep)
        sub = hbr.replace(middle=hbr.middle.replace(filled=jnp.asarray(mask)),
                          middle_patterns=jnp.where(jnp.asarray(mask), hbr.middle_patterns, -1))
        began = time.time()
        mod = modulate(robot, sub, task, standing_state(robot), skills=skills, patterns=allowed_patterns(), chunk=4096,
                       progress=False, table=planning_table(sub))
        s = mod.summary()
        row = {"elites": int(mask.sum()), "median_error_m": s["median_error_m"],
               "share_within_0.1": s["mean_patterns_per_skill_within_radius_m"]["0.1"]["share_of_shown"],
               "shown": s["mean_patterns_shown_per_skill"], "seconds": time.time() - began}
        out[f"{name}_keep{keep}"] = row
        print(name, keep, row, flush=True)
json.dump(out, open(sys.argv[2], "w"), indent=1)
