#!/usr/bin/env python3
"""Score `auto`'s cost model on measured frames, and search a grid of its constants.

Reads the tables that `rayd bench SCENE --frames 4 --accel dacrt,dacrt-sampled,mbvh8
--build fast --sets primary,diffuse2 --rays-per-frame 65536,262144,1048576 --threads 1,2
--format table` prints (BENCHMARKS.md §8), one file per run and scene, and for every
situation (set, threads, rays; geometry new or refittable) compares the model's pick with
the fastest measured strategy. Prints the score of the constants in `src/accel/auto.rs`,
the best point of the grid over all files, and that search with each run held out in
turn (files whose names share the prefix before the first `_` are one run) and with each
scene held out in turn.

    scripts/fit_auto.py r1_dragon.txt r1_brainstem.txt r2_dragon.txt ...
    git show 7eb0892:src/accel/auto.rs > old.rs; scripts/fit_auto.py --model old.rs --score-only r*.txt

Static batches (one trace of rays already in memory, with a build of the quality asked
for) are a second kind of situation: `--static static.csv` adds the rows that
`rayd bench SCENE --accel auto,mbvh8,dacrt-sampled --sets primary,ao,diffuse2 --threads
1,2 --runs 3 --width W --height H --format json` reports (BENCHMARKS.md §39; `--save-static`
turns such reports into those rows), scores the model's picks on them beside the moving
frames, and `--floors` scores each `shape_floor` in turn over both kinds:

    scripts/fit_auto.py --static docs/experiments/auto-fit/static.csv --floors docs/experiments/auto-fit/r*.txt

Needs numpy: the grid has about a million points.
"""
import argparse
import itertools
import math
import os
import re
import sys

import numpy as np

# The strategies `rayd bench` measures `auto` against (src/bench/dynamic.rs, `candidates`;
# brute is never measured here): for new geometry a rebuild, for refittable geometry a
# refit, and both DACRT cores either way.
CANDIDATES = {
    False: [("mbvh8", "rebuild"), ("dacrt", "update"), ("dacrt-sampled", "update")],
    True: [("mbvh8", "refit"), ("dacrt", "update"), ("dacrt-sampled", "update")],
}
STRATEGIES = [("mbvh8", "rebuild"), ("mbvh8", "refit"), ("dacrt-sampled", "update")]

# The largest RMS log error a searched point may have on any strategy's frame times (0.25:
# most predictions within about 25%). Ranking alone can drift far from the times: it once
# found constants that picked as well as any while predicting DACRT's frames at twice
# their time, and such constants mispredict every job unlike the fitted ones (a `sah`
# build that one frame alone must repay, a scene of another size).
MAX_ERROR = 0.25


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


MODEL_RS = os.path.join(os.path.dirname(__file__), "..", "src", "accel", "auto.rs")


def current(path=MODEL_RS):
    """The MODEL constants of `path` (src/accel/auto.rs, or an earlier version of it:
    `git show COMMIT:src/accel/auto.rs`; constants it lacks take the value that leaves
    the model as it was before them)."""
    src = open(path).read()
    block = src[src.index("const MODEL: Model"):]
    block = block[:block.index("};")]
    absent = {"ray_shape": "0.0, 0.0", "trace": "1.0, 1.0, 1.0", "shape_floor": "12.0",
              "first_hit": "1.0"}

    def num(k):
        m = re.search(k + r": \[?([^\]\n]+)\]?,", block)
        return [float(x) for x in (m.group(1) if m else absent[k]).split(",")]
    return dict(build=num("build")[0], refit=num("refit")[0], bvh_ray=num("bvh_ray")[0],
                slow=num("refit_slowdown")[0], pre=num("dacrt_pre")[0], top=num("dacrt_top")[0],
                dacrt_ray=num("dacrt_ray")[0], s_b=num("speedup2")[0], s_t=num("speedup2")[1],
                s_d=num("speedup2")[2], e_b=num("ray_shape")[0], e_d=num("ray_shape")[1],
                lo=num("shape_floor")[0], builds=num("build"), traces=num("trace"),
                first_hit=num("first_hit")[0])


def _terms(p, tris, threads):
    """The model's thread speed-up (of a 2-thread speed-up) and its bent log₂ T (of an
    exponent), as src/accel/auto.rs's `speedup` and `shaped`."""
    lg = np.maximum(np.log2(tris), 1.0)
    return (lambda s2: threads ** np.log2(s2),
            lambda e: lg * (np.clip(lg, p["lo"], 20.0) / 16.0) ** e)


def predict(p, tris, threads, rays):
    """The model's frame seconds of each strategy (src/accel/auto.rs's `predict`, one
    frame standing alone, one batch). Works on numbers and on broadcasting numpy arrays."""
    sp, shape = _terms(p, tris, threads)
    bvh_trace = rays * p["bvh_ray"] * shape(p["e_b"]) / sp(p["s_t"])
    return {
        ("mbvh8", "rebuild"): p["build"] * tris / sp(p["s_b"]) + bvh_trace,
        ("mbvh8", "refit"): p["refit"] * tris / sp(p["s_b"]) + bvh_trace * p["slow"],
        ("dacrt-sampled", "update"): (p["pre"] * tris + p["top"] * tris
                                      + rays * p["dacrt_ray"] * shape(p["e_d"])) / sp(p["s_d"]),
    }


class Situations:
    """The measured situations as columns: one per (situation, new or refittable)."""

    def __init__(self, sits):
        cols = {k: [] for k in ("tris", "threads", "rays", "refit", "bvh_ms", "dacrt_ms", "best_ms",
                                "bvh_best", "dacrt_best")}
        self.times = {k: ([], [], [], []) for k in STRATEGIES}  # tris, threads, rays, ms
        for (_, tris, _, threads, rays), ms in sits.items():
            for k in STRATEGIES:
                if k in ms:
                    for col, v in zip(self.times[k], (tris, threads, rays, ms[k])):
                        col.append(v)
            for refittable in (False, True):
                bvh = CANDIDATES[refittable][0]
                cands = [c for c in CANDIDATES[refittable] if c in ms]
                if len(cands) < 2 or bvh not in ms or ("dacrt-sampled", "update") not in ms:
                    continue
                best = min(cands, key=lambda c: ms[c])
                for col, v in zip(cols.values(), (tris, threads, rays, refittable, ms[bvh],
                                                  ms[("dacrt-sampled", "update")], ms[best],
                                                  best == bvh,
                                                  best == ("dacrt-sampled", "update"))):
                    col.append(v)
        self.c = {k: np.array(v, dtype=float) for k, v in cols.items()}
        self.times = {k: tuple(np.array(c, dtype=float) for c in v) for k, v in self.times.items()}
        self.n = len(self.c["tris"])


def score(p, s):
    """(right picks, situations, mean cost of wrong picks, worst cost), as `rayd bench`
    scores them; with array-valued constants (shape (N, 1)), arrays of N each."""
    c = s.c
    t = predict(p, c["tris"], c["threads"], c["rays"])
    bvh = np.where(c["refit"] > 0, t[("mbvh8", "refit")], t[("mbvh8", "rebuild")])
    dacrt = t[("dacrt-sampled", "update")] < bvh
    right = np.where(dacrt, c["dacrt_best"], c["bvh_best"]) > 0
    cost = np.where(dacrt, c["dacrt_ms"], c["bvh_ms"]) / c["best_ms"]
    wrong = ~right
    nwrong = wrong.sum(axis=-1)
    mean = np.where(nwrong > 0, (cost * wrong).sum(axis=-1) / np.maximum(nwrong, 1), 1.0)
    worst = np.where(wrong, cost, 1.0).max(axis=-1)
    return right.sum(axis=-1), s.n, mean, worst


def errors(p, s):
    """Per strategy, the root mean square of ln(predicted / measured) frame time."""
    out = {}
    for k, (tris, threads, rays, ms) in s.times.items():
        e = np.log(predict(p, tris, threads, rays)[k] * 1000.0 / ms)
        out[k] = np.sqrt((e * e).mean(axis=-1))
    return out


# DACRT per batch and per ray, its 2-thread speed-up, the trace's, the `fast` build per
# triangle, the refit slowdown, the BVH per ray, and how the BVH's and DACRT's per-ray
# costs bend with log₂ T (exponents of log₂ T / 16).
GRID = {
    "top": [0.1e-6, 0.15e-6, 0.2e-6, 0.3e-6, 0.5e-6],
    "dacrt_ray": [10e-9, 11e-9, 12e-9, 13e-9, 14e-9],
    "s_d": [1.4, 1.5, 1.6, 1.7],
    "s_t": [1.6, 1.7, 1.8],
    "build": [0.09e-6, 0.11e-6, 0.13e-6],
    "slow": [1.05, 1.1, 1.15],
    "bvh_ray": [12e-9, 13.5e-9, 15e-9],
    "e_b": [0.0, 0.5, 1.0],
    "e_d": [0.0, 0.5, 1.0, 1.5, 2.0],
}


def search(base, s):
    """The grid point with the most right picks (then the cheapest wrong ones) among
    those that also predict every strategy's times within MAX_ERROR."""
    names = list(GRID)
    points = np.array(list(itertools.product(*GRID.values())))
    best = None
    for chunk in np.array_split(points, max(1, len(points) // 20000)):
        p = dict(base, **{n: chunk[:, i:i + 1] for i, n in enumerate(names)})
        ok, _, mean, _ = score(p, s)
        err = np.max(np.stack([e.ravel() for e in errors(p, s).values()]), axis=0)
        key = np.where(err <= MAX_ERROR, ok * 1000.0 - mean, -np.inf)
        i = int(np.argmax(key))
        if np.isfinite(key[i]) and (best is None or key[i] > best[0]):
            best = (key[i], dict(base, **{n: float(chunk[i, j]) for j, n in enumerate(names)}))
    return best[1]


def show(p, s):
    ok, n, mean, worst = score(p, s)
    err = {f"{a} {m}": round(float(v), 3) for (a, m), v in errors(p, s).items()}
    return f"{int(ok)} of {n} right, wrong picks {float(mean):.3f}× (worst {float(worst):.2f}×); errors {err}"


QUALITIES = ["fast", "sah", "sbvh"]


def parse_static(path):
    """{(run, scene, set, threads, rays): {"mbvh8": ms, "dacrt-sampled": ms, ...}} from a CSV
    of static bench rows (build and trace of one batch: a BVH's build is paid by the batch,
    DACRT's precompute likewise)."""
    import csv
    out = {}
    for row in csv.DictReader(open(path)):
        key = (row["run"], row["scene"], row["set"], int(row["threads"]), int(row["rays"]))
        d = out.setdefault(key, {"tris": int(row["traced_triangles"]), "quality": row["build"],
                                 "first_hit": row["set"] == "ao"})
        d[row["accel"]] = float(row["build_ms"]) + float(row["trace_ms"])
    return {k: v for k, v in out.items() if "mbvh8" in v and "dacrt-sampled" in v}


def save_static(reports, path):
    """Writes the rows of `rayd bench --format json` reports (each named RUN-anything.json;
    RUN becomes the row's run) as the CSV that `parse_static` reads."""
    import csv
    import json
    w = csv.writer(open(path, "w"))
    w.writerow(["run", "scene", "traced_triangles", "build", "set", "threads", "rays", "accel",
                "build_ms", "trace_ms"])
    for f in sorted(reports):
        d = json.load(open(f))
        run = os.path.basename(f).split("-")[0]
        for sc in d["scenes"]:
            b = {(x["accel"], x["threads"]): x["seconds"] for x in sc["builds"]}
            for x in sc["results"]:
                w.writerow([run, os.path.basename(sc["scene"]), sc["traced_triangles"], d["build"],
                            x["set"], x["threads"], x["rays"], x["accel"],
                            "%.6f" % (b[(x["accel"], x["threads"])] * 1e3),
                            "%.6f" % (x["seconds"] * 1e3)])


def score_static(p, sits):
    """(right picks, situations, mean cost of every pick, worst) of `auto`'s model on static
    batches: a new structure of the batch's quality against DACRT (`predict` in
    src/accel/auto.rs with `Geometry::New`, one frame, one batch)."""
    v = list(sits.values())
    tris = np.array([x["tris"] for x in v], dtype=float)
    threads = np.array([k[3] for k in sits], dtype=float)
    rays = np.array([k[4] for k in sits], dtype=float)
    q = np.array([QUALITIES.index(x["quality"]) for x in v])
    fh = np.array([x["first_hit"] for x in v])
    bvh_ms = np.array([x["mbvh8"] for x in v])
    dacrt_ms = np.array([x["dacrt-sampled"] for x in v])
    sp, shape = _terms(p, tris, threads)
    bvh = (np.array(p["builds"])[q] * tris / sp(p["s_b"])
           + rays * p["bvh_ray"] * np.array(p["traces"])[q] * shape(p["e_b"])
           * np.where(fh, p["first_hit"], 1.0) / sp(p["s_t"]))
    dacrt = (p["pre"] * tris + p["top"] * tris + rays * p["dacrt_ray"] * shape(p["e_d"])) / sp(p["s_d"])
    got = np.where(dacrt < bvh, dacrt_ms, bvh_ms)
    cost = got / np.minimum(bvh_ms, dacrt_ms)
    return int((cost <= 1.0).sum()), len(cost), float(cost.mean()), float(cost.max())


def floors(base, every, static):
    """Each `shape_floor` scored over the moving frames and the static batches."""
    for lo in [12.0, 13.0, 14.0, 14.5, 15.0, 15.5, 16.0]:
        p = dict(base, lo=lo)
        ok, n, mean, _ = score(p, every)
        line = f"shape_floor {lo}: frames {int(ok)} of {n}, wrong picks {float(mean):.3f}×"
        if static:
            sok, sn, smean, sworst = score_static(p, static)
            line += f"; static {sok} of {sn}, mean pick {smean:.3f}× the best (worst {sworst:.2f}×)"
        print(line)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("tables", nargs="*")
    ap.add_argument("--model", default=MODEL_RS,
                    help="the auto.rs whose constants are scored (default: this checkout's)")
    ap.add_argument("--score-only", action="store_true", help="score them; no search")
    ap.add_argument("--static", action="append", default=[],
                    help="a CSV of static batches (see --save-static) to score as well")
    ap.add_argument("--save-static", nargs=2, metavar=("OUT", "REPORTS"),
                    help="write the CSV of the bench reports matched by the glob REPORTS, and stop")
    ap.add_argument("--floors", action="store_true",
                    help="score each shape_floor over both kinds of situation; no search")
    args = ap.parse_args()
    if args.save_static:
        import glob
        save_static(glob.glob(args.save_static[1]), args.save_static[0])
        return
    sits = {}
    for f in args.tables:
        sits.update(parse(f))
    every = Situations(sits)
    base = current(args.model)
    static = {}
    for f in args.static:
        static.update(parse_static(f))
    print(f"{args.model}:", show(base, every), base)
    if static:
        ok, n, mean, worst = score_static(base, static)
        print(f"static batches: {ok} of {n} right, mean pick {mean:.3f}× the best (worst {worst:.2f}×)")
    if args.floors:
        floors(base, every, static)
        return
    if args.score_only:
        return
    p = search(base, every)
    print("grid best, in sample:", show(p, every), p)
    # A run is the files sharing a name's prefix before `_`; a scene, its triangle count.
    groups = (("run", lambda key: os.path.basename(key[0]).split("_")[0]),
              ("scene", lambda key: f"of {key[1]} triangles"))
    for label, group in groups:
        held = [0, 0]
        for r in sorted({group(k) for k in sits}):
            fit = Situations({k: v for k, v in sits.items() if group(k) != r})
            test = Situations({k: v for k, v in sits.items() if group(k) == r})
            ok, n, mean, _ = score(search(base, fit), test)
            print(f"{label} {r} held out: {int(ok)} of {n}, wrong picks {float(mean):.3f}×")
            held[0] += int(ok)
            held[1] += n
        print(f"held out by {label}, all: {held[0]} of {held[1]}")


if __name__ == "__main__":
    main()
