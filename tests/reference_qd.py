"""Brute-force NumPy references of the containers' insertion rules, written from their docstrings.

Plain Python loops over individuals and slots, float32 arithmetic in the same order as the
documented formulas, so results must match the JAX containers exactly.
"""

import math

import numpy as np

f32 = np.float32


def _insertable(fit, desc, valid, low, high):
    return bool(valid) and math.isfinite(fit) and all(math.isfinite(v) for v in desc) and all(
        lo <= v <= hi for v, lo, hi in zip(desc, low, high)
    )


def grid_add(bins, low, high, rep, genotypes, descriptors, fitnesses, valid):
    """rep: dict of numpy arrays (genotypes, descriptors, fitnesses, filled). Returns (rep, slots)."""
    rep = {k: v.copy() for k, v in rep.items()}
    strides = [int(np.prod(bins[i + 1 :])) for i in range(len(bins))]
    best = {}  # cell -> batch index of the best candidate (first on ties)
    cells = []
    for i, (desc, fit) in enumerate(zip(descriptors, fitnesses)):
        if not _insertable(fit, desc, valid[i], low, high):
            cells.append(-1)
            continue
        cell = 0
        for d, (v, lo, hi, b) in enumerate(zip(desc, low, high, bins)):
            scaled = (f32(v) - f32(lo)) / (f32(hi) - f32(lo)) * f32(b)
            cell += min(max(int(math.floor(scaled)), 0), b - 1) * strides[d]
        cells.append(cell)
        if cell not in best or fit > fitnesses[best[cell]]:
            best[cell] = i
    slots = np.full(len(fitnesses), -1)
    for cell, i in best.items():
        if fitnesses[i] > rep["fitnesses"][cell]:
            slots[i] = cell
            rep["genotypes"][cell] = genotypes[i]
            rep["descriptors"][cell] = descriptors[i]
            rep["fitnesses"][cell] = fitnesses[i]
            rep["filled"][cell] = True
    return rep, slots


def _dist(a, b):
    total = f32(0.0)
    for x, y in zip(a, b):
        diff = f32(x) - f32(y)
        total = f32(total + f32(diff * diff))
    return f32(np.sqrt(total))


def _mean(values):
    finite = [v for v in values if math.isfinite(v)]
    if not finite:
        return f32(0.0)
    total = f32(0.0)
    for v in finite:
        total = f32(total + v)
    return f32(total / f32(len(finite)))


def _sorted_neighbours(point, rep, exclude=-1):
    """(distance, slot) of all filled slots except `exclude`, nearest first, ties to lower slot."""
    pairs = [(_dist(point, rep["descriptors"][s]), s) for s in np.flatnonzero(rep["filled"]) if s != exclude]
    return sorted(pairs, key=lambda p: (p[0], p[1]))


def archive_add(capacity, low, high, l, k, eps, rep, genotypes, descriptors, fitnesses, valid):
    """Batched unstructured-archive insertion (rules in hte_jax/qd/archive.py). Returns (rep, slots)."""
    rep = {key: v.copy() for key, v in rep.items()}
    l, eps = f32(l), f32(eps)
    size = int(rep["filled"].sum())
    batch = len(fitnesses)
    decision = ["reject"] * batch
    nearest = [-1] * batch
    for i in range(batch):
        fit, desc = f32(fitnesses[i]), descriptors[i]
        if not _insertable(fit, desc, valid[i], low, high):
            continue
        neigh = _sorted_neighbours(desc, rep)
        if size == 0 or neigh[0][0] > l:
            decision[i] = "new"
            continue
        if size == 1 or neigh[1][0] < f32(f32(1.0) - eps) * l:
            continue
        nn = neigh[0][1]
        nov_c = _mean([d for d, _ in neigh[1 : k + 1]])
        nov_n = _mean([d for d, _ in _sorted_neighbours(rep["descriptors"][nn], rep, exclude=nn)[:k]])
        fit_n = f32(rep["fitnesses"][nn])
        dominates = (
            fit >= f32(f32(1.0) - f32(np.sign(fit_n)) * eps) * fit_n
            and nov_c >= f32(f32(1.0) - f32(np.sign(nov_n)) * eps) * nov_n
            and f32(f32(fit - fit_n) * abs(nov_n)) > f32(-f32(nov_c - nov_n) * abs(fit_n))
        )
        if dominates:
            decision[i], nearest[i] = "replace", nn
    # replacements of the same elite: the highest fitness, then the first in the batch
    for i in range(batch):
        if decision[i] == "replace":
            rivals = [j for j in range(batch) if decision[j] == "replace" and nearest[j] == nearest[i]]
            if i != max(rivals, key=lambda j: (fitnesses[j], -j)):
                decision[i] = "lost"
    # accepted candidates within l of a higher-ranked accepted one are dropped
    kept = [i for i in range(batch) if decision[i] in ("new", "replace")]
    survivors = [
        i
        for i in kept
        if not any(
            j != i
            and _dist(descriptors[j], descriptors[i]) <= l
            and (fitnesses[j] > fitnesses[i] or (fitnesses[j] == fitnesses[i] and j < i))
            for j in kept
        )
    ]
    slots = np.full(batch, -1)
    free = size
    for i in survivors:  # increasing batch order
        if decision[i] == "replace":
            slots[i] = nearest[i]
        elif free < capacity:
            slots[i] = free
            free += 1
    for i in np.flatnonzero(slots >= 0):
        s = slots[i]
        rep["genotypes"][s] = genotypes[i]
        rep["descriptors"][s] = descriptors[i]
        rep["fitnesses"][s] = fitnesses[i]
        rep["filled"][s] = True
    return rep, slots
