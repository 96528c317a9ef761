"""Study: where one maze_eval action's GPU time goes, from a jax.profiler trace (kernels per name, GPU busy time).

    python studies/profile_action.py hte-jax gpu 3 out.json   # protocol, preset, traced actions, JSON
"""
import collections, glob, json, os, sys, tempfile, time
sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "benchmarks"))
import jax
from action_time import measure
from jax.profiler import ProfileData

protocol, preset, actions, out = sys.argv[1], sys.argv[2], int(sys.argv[3]), sys.argv[4]
print("warm-up", json.dumps({k: v for k, v in measure(protocol, preset, 2, 0).items() if "median" in k}), flush=True)
d = tempfile.mkdtemp()
with jax.profiler.trace(d):
    m = measure(protocol, preset, actions, 0)
print("traced", json.dumps({k: v for k, v in m.items() if "median" in k or k in ("plan_s", "act_s")}), flush=True)
path = glob.glob(d + "/**/*.xplane.pb", recursive=True)[0]
pd = ProfileData.from_file(path)
report = {}
for plane in pd.planes:
    if not plane.name.startswith("/device:GPU"):
        continue
    lines = {l.name: list(l.events) for l in plane.lines}
    print(plane.name, {k: len(v) for k, v in lines.items()})
    modules = sorted(((e.start_ns, e.start_ns + e.duration_ns, e.name) for e in lines.get("XLA Modules", [])))
    kernels = [e for name, evs in lines.items() if name.startswith("Stream") for e in evs]
    per_module = collections.defaultdict(lambda: {"wall_ns": 0.0, "calls": 0, "kernel_ns": 0.0, "kernels": 0,
                                                  "by_name": collections.Counter(), "count": collections.Counter()})
    for s, e, n in modules:
        per_module[n]["wall_ns"] += e - s
        per_module[n]["calls"] += 1
    import bisect
    starts = [m[0] for m in modules]
    for k in kernels:
        i = bisect.bisect_right(starts, k.start_ns) - 1
        name = modules[i][2] if i >= 0 and k.start_ns <= modules[i][1] else "(outside)"
        pm = per_module[name]
        pm["kernel_ns"] += k.duration_ns
        pm["kernels"] += 1
        pm["by_name"][k.name] += k.duration_ns
        pm["count"][k.name] += 1
    for n, pm in sorted(per_module.items(), key=lambda x: -x[1]["wall_ns"]):
        print(f"\nmodule {n[:80]}: calls {pm['calls']} wall {pm['wall_ns']/1e9:.3f} s, kernels {pm['kernels']} "
              f"busy {pm['kernel_ns']/1e9:.3f} s")
        for kn, t in pm["by_name"].most_common(25):
            print(f"   {t/1e6:9.1f} ms  x{pm['count'][kn]:<7d} {kn[:110]}")
        report[n] = {"calls": pm["calls"], "wall_s": pm["wall_ns"] / 1e9, "kernels": pm["kernels"],
                     "busy_s": pm["kernel_ns"] / 1e9,
                     "top": [[kn, t / 1e9, pm["count"][kn]] for kn, t in pm["by_name"].most_common(40)]}
    break
json.dump({"measure": m, "modules": report}, open(out, "w"), indent=1)
