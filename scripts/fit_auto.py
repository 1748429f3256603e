#!/usr/bin/env python3
"""Score `auto`'s cost model on measured frames, and search a grid of its constants.

Reads the tables that `rayd bench SCENE --frames 4 --accel dacrt,dacrt-sampled,mbvh8
--build fast --sets primary,diffuse2 --rays-per-frame 65536,262144,1048576 --threads 1,2
--format table` prints (BENCHMARKS.md §8), one file per run and scene, and for every
situation (set, threads, rays; geometry new or refittable) compares the model's pick with
the fastest measured strategy. Prints the score of the constants in `src/accel/auto.rs`,
the best point of the grid over all files, and that search with each run held out in
turn (files whose names share the prefix before the first `_` are one run).

    scripts/fit_auto.py r1_dragon.txt r1_brainstem.txt r2_dragon.txt ...
"""
import itertools
import math
import os
import re
import sys

# The strategies `rayd bench` measures `auto` against (src/bench/dynamic.rs, `candidates`;
# brute is never measured here): for new geometry a rebuild, for refittable geometry a
# refit, and both DACRT cores either way.
CANDIDATES = {
    False: [("mbvh8", "rebuild"), ("dacrt", "update"), ("dacrt-sampled", "update")],
    True: [("mbvh8", "refit"), ("dacrt", "update"), ("dacrt-sampled", "update")],
}


def parse(path):
    """{(file, triangles, set, threads, rays): {(accel, mode): frame ms}}"""
    out, tris, cur = {}, None, None
    for line in open(path):
        m = re.match(r"^\S+ — (\d+) triangles", line)
        if m:
            tris = int(m.group(1)) + 12
            continue
        m = re.match(r"^(\w+) rays, (\d+) thread", line)
        if m:
            cur = (m.group(1), int(m.group(2)))
            continue
        m = re.match(r"^\| (dacrt-sampled|dacrt|mbvh8) \| (update|rebuild|refit) \| [\d.]+ \| (.*)$",
                     line)
        if m and cur and tris:
            cells = [float(c.split()[0]) for c in m.group(3).split("|")[:3]]
            for rays, ms in zip([65536, 262144, 1048576], cells):
                out.setdefault((path, tris, cur[0], cur[1], rays), {})[(m.group(1), m.group(2))] = ms
    return out


def current():
    """The MODEL constants of src/accel/auto.rs."""
    src = open(os.path.join(os.path.dirname(__file__), "..", "src", "accel", "auto.rs")).read()
    block = src[src.index("const MODEL: Model"):]
    block = block[:block.index("};")]
    num = lambda k: [float(x) for x in re.search(k + r": \[?([^\]\n]+)\]?,", block).group(1).split(",")]
    return dict(build=num("build")[0], refit=num("refit")[0], bvh_ray=num("bvh_ray")[0],
                slow=num("refit_slowdown")[0], pre=num("dacrt_pre")[0], top=num("dacrt_top")[0],
                dacrt_ray=num("dacrt_ray")[0], s_b=num("speedup2")[0], s_t=num("speedup2")[1],
                s_d=num("speedup2")[2])


def predict(p, tris, threads, rays):
    """The model's frame seconds of each strategy (src/accel/auto.rs's `predict`, one
    frame standing alone, one batch)."""
    sp = lambda s2: threads ** math.log2(s2)
    lg = max(math.log2(tris), 1.0)
    return {
        ("mbvh8", "rebuild"): p["build"] * tris / sp(p["s_b"])
        + rays * p["bvh_ray"] * lg / sp(p["s_t"]),
        ("mbvh8", "refit"): p["refit"] * tris / sp(p["s_b"])
        + rays * p["bvh_ray"] * lg * p["slow"] / sp(p["s_t"]),
        ("dacrt-sampled", "update"): (p["pre"] * tris + p["top"] * tris
                                      + rays * p["dacrt_ray"] * lg) / sp(p["s_d"]),
    }


def pick(p, tris, threads, rays, refittable):
    """What `choose` runs: `mbvh8` (a refit of refittable geometry, else a rebuild) or
    `dacrt-sampled`."""
    t = predict(p, tris, threads, rays)
    bvh = t[("mbvh8", "refit" if refittable else "rebuild")]
    if t[("dacrt-sampled", "update")] < bvh:
        return ("dacrt-sampled", "update")
    return ("mbvh8", "refit" if refittable else "rebuild")


def errors(p, sits):
    """Per strategy, the root mean square of ln(predicted / measured) frame time: a fit
    that only ranks strategies can drift far from the times themselves (one that picked as
    well as any predicted DACRT's frames at twice their time), and then mispredicts every
    job unlike the fitted ones, such as a `sah` build that one frame alone must repay."""
    out = {}
    for (_, tris, _, threads, rays), ms in sits.items():
        for k, sec in predict(p, tris, threads, rays).items():
            if k in ms:
                out.setdefault(k, []).append(math.log(sec * 1000.0 / ms[k]))
    return {k: math.sqrt(sum(e * e for e in v) / len(v)) for k, v in out.items()}


def score(p, sits):
    """(right picks, situations, mean cost of wrong picks, worst cost), as `rayd bench`
    scores them."""
    ok, n, costs = 0, 0, []
    for (_, tris, _, threads, rays), ms in sits.items():
        for refittable in (False, True):
            cands = [c for c in CANDIDATES[refittable] if c in ms]
            chosen = pick(p, tris, threads, rays, refittable)
            if len(cands) < 2 or chosen not in ms:
                continue
            best = min(cands, key=lambda c: ms[c])
            n += 1
            if chosen == best:
                ok += 1
            else:
                costs.append(ms[chosen] / ms[best])
    return ok, n, (sum(costs) / len(costs) if costs else 1.0), max(costs or [1.0])


# DACRT per batch and per ray, its 2-thread speed-up, the trace's, the `fast` build per
# triangle, the refit slowdown, the BVH per ray.
GRID = list(itertools.product([0.1e-6, 0.15e-6, 0.2e-6, 0.3e-6, 0.5e-6, 0.85e-6],
                              [10e-9, 11e-9, 12e-9, 13e-9, 14e-9], [1.4, 1.5, 1.6, 1.7],
                              [1.6, 1.7, 1.8], [0.09e-6, 0.11e-6, 0.13e-6],
                              [1.05, 1.1, 1.15], [12e-9, 13.5e-9, 15e-9]))

# The largest RMS log error a searched point may have on any strategy's times (0.25: a
# quarter of its predictions off by more than about 28%).
MAX_ERROR = 0.25


def search(base, sits):
    """The grid point with the most right picks (then the cheapest wrong ones) among
    those that also predict every strategy's times within MAX_ERROR."""
    best = None
    for top, dr, sd, st, build, slow, br in GRID:
        p = dict(base, top=top, dacrt_ray=dr, s_d=sd, s_t=st, build=build, slow=slow,
                 bvh_ray=br)
        s = score(p, sits)
        if best is not None and (s[0], -s[2]) <= (best[1][0], -best[1][2]):
            continue
        if max(errors(p, sits).values()) <= MAX_ERROR:
            best = (p, s)
    return best


def main():
    sits = {}
    for f in sys.argv[1:]:
        sits.update(parse(f))
    base = current()
    fmt = lambda e: {f"{a} {m}": round(v, 3) for (a, m), v in e.items()}
    print("src/accel/auto.rs:", score(base, sits), base, "errors:", fmt(errors(base, sits)))
    p, s = search(base, sits)
    print("grid best, in sample:", s, p, "errors:", fmt(errors(p, sits)))
    run = lambda key: os.path.basename(key[0]).split("_")[0]
    held = [0, 0]
    for r in sorted({run(k) for k in sits}):
        p, _ = search(base, {k: v for k, v in sits.items() if run(k) != r})
        s = score(p, {k: v for k, v in sits.items() if run(k) == r})
        print(f"run {r} held out:", s)
        held[0] += s[0]
        held[1] += s[1]
    print("held out, all runs:", held)


if __name__ == "__main__":
    main()
