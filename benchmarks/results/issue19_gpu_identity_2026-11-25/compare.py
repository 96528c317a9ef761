"""Compare tests/sharding_script.py's arrays across device counts: for every array, bit-identical or
the largest absolute difference. python compare.py OUT.npz [OUT2.npz ...] (prints a JSON summary)."""
import json
import sys

import numpy as np

summary = {}
for path in sys.argv[1:]:
    data = np.load(path)
    runs = {}
    for key in data.files:
        parts = key.split("/", 2)
        if len(parts) == 3 and parts[1].isdigit():
            runs.setdefault(parts[0], {}).setdefault(int(parts[1]), {})[parts[2]] = data[key]
    for part, by_count in runs.items():
        ref = by_count[min(by_count)]
        for count, arrays in sorted(by_count.items()):
            if count == min(by_count):
                continue
            diffs = {}
            for name, a in ref.items():
                b = arrays[name]
                same = a.shape == b.shape and np.array_equal(a, b, equal_nan=True)
                if not same:
                    diffs[name] = float(np.nanmax(np.abs(a.astype(np.float64) - b.astype(np.float64)))) if a.shape == b.shape else "shape"
            summary[f"{part}: {count} vs {min(by_count)} devices"] = {"arrays": len(ref), "identical": len(ref) - len(diffs), "differ": diffs}
    summary |= {k: float(data[k]) for k in data.files if k.startswith("seconds/")}
print(json.dumps(summary, indent=1))
