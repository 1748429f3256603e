#!/usr/bin/env python3
"""Measures issue 9's two renderer speed goals with `rayd render` and prints Markdown tables.

1. Where a path-traced frame's time goes: the renderer should spend at least half of it
   inside the intersector (`trace_seconds`), shading, sampling and wave bookkeeping
   (`shade_seconds`) the rest. One frame per scene, on 1 and on 2 threads.
2. An animated sequence (BrainStem, 262,144 rays per frame: 512x512 primary rays): the
   whole frame (evaluate + prepare + trace + shade) with `--accel auto --update auto`
   against every BVH rebuilt every frame (`--update rebuild`, each build quality) and
   Embree rebuilt at LOW (`--build fast`) every frame. Frame 0 is left out (every strategy
   builds or precomputes there from nothing); the median of the rest is reported.

Every configuration runs in this one invocation, so the ratios compare like with like on a
shared, noisy machine.

    python3 scripts/render_goals.py                # both goals
    python3 scripts/render_goals.py --only shade   # goal 1 only
    RAYD=target/release/rayd python3 scripts/render_goals.py --frames 0:1:0.125

Needs target/release/rayd built with `--features embree` for the Embree rows (they are
skipped, and said to be, when the binary has no Embree).
"""

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
SCENES = ROOT.parent / "shared" / "scenes"


def render(rayd, scene, out_dir, args):
    """Runs one `rayd render` and returns its JSON report, or None if it failed."""
    out = Path(out_dir) / "frame-####.png"
    cmd = [rayd, "render", str(scene), "--out", str(out)] + args
    p = subprocess.run(cmd, capture_output=True, text=True)
    if p.returncode != 0:
        print(f"  failed: {' '.join(cmd)}: {p.stderr.strip()}", file=sys.stderr)
        return None
    return json.loads(p.stdout)


def shade_goal(rayd, threads_list, size, spp, bounces):
    """Goal 1: trace share of a path-traced frame."""
    print("### Where a path-traced frame's time goes\n")
    print(
        f"`--integrator path --bounces {bounces} --spp {spp}`, {size[0]}x{size[1]}, "
        "one frame; trace = inside the intersector, shade = shading, sampling and wave "
        "bookkeeping.\n"
    )
    print("| scene | threads | rays | trace s | shade s | trace share | goal ≥ 0.5 |")
    print("|---|---|---|---|---|---|---|")
    for name in ["DamagedHelmet.glb", "ReciprocatingSaw.glb", "BrainStem.glb"]:
        scene = SCENES / name
        if not scene.exists():
            print(f"| {name} | — | absent | | | | |")
            continue
        for threads in threads_list:
            with tempfile.TemporaryDirectory() as d:
                r = render(
                    rayd,
                    scene,
                    d,
                    [
                        "--integrator", "path", "--bounces", str(bounces),
                        "--spp", str(spp), "--width", str(size[0]),
                        "--height", str(size[1]), "--threads", str(threads),
                        "--frames", "0:0:1",
                    ],
                )
            if r is None:
                continue
            f = r["frames"][0]
            share = f["trace_seconds"] / (f["trace_seconds"] + f["shade_seconds"])
            print(
                f"| {name} | {threads} | {f['rays']} | {f['trace_seconds']:.3f} | "
                f"{f['shade_seconds']:.3f} | {share:.2f} | {'met' if share >= 0.5 else 'not met'} |"
            )
    print()


def frame_goal(rayd, threads, frames, has_embree):
    """Goal 2: a whole animated frame, auto against rebuilds."""
    scene = SCENES / "BrainStem.glb"
    if not scene.exists():
        print("BrainStem.glb is absent: the sequence goal is not measured")
        return
    configs = [("auto", ["--accel", "auto", "--update", "auto"])]
    for accel in ["mbvh8", "mbvh4", "bvh2"]:
        for build in ["fast", "sah", "sbvh"]:
            configs.append(
                (f"{accel} {build} rebuilt", ["--accel", accel, "--build", build, "--update", "rebuild"])
            )
    for accel in ["dacrt", "dacrt-sampled"]:
        configs.append((accel, ["--accel", accel]))
    configs.append(("mbvh8 sah refitted", ["--accel", "mbvh8", "--update", "refit"]))
    if has_embree:
        configs.append(("embree LOW rebuilt", ["--accel", "embree", "--build", "fast"]))
    print(f"### A BrainStem frame, 512x512 primary rays (262,144), {threads} threads\n")
    print(
        f"`--frames {frames}`; the median over frames 1.. of each phase, in ms "
        "(frame 0 builds from nothing and is left out).\n"
    )
    print("| strategy | what ran | evaluate | prepare | trace | shade | frame | vs auto |")
    print("|---|---|---|---|---|---|---|---|")
    rows = []
    # One discarded run first: the first render after a pause reads slow (session 13 saw
    # the first-measured row, auto, at three times its shade in two loops of thirteen runs).
    with tempfile.TemporaryDirectory() as d:
        render(rayd, scene, d, ["--integrator", "primary", "--width", "512", "--height", "512",
                                "--threads", str(threads), "--frames", frames] + configs[0][1])
    for label, extra in configs:
        with tempfile.TemporaryDirectory() as d:
            r = render(
                rayd,
                scene,
                d,
                ["--integrator", "primary", "--width", "512", "--height", "512",
                 "--threads", str(threads), "--frames", frames] + extra,
            )
        if r is None:
            continue
        later = r["frames"][1:]
        med = {
            k: statistics.median(f[k] for f in later) * 1e3
            for k in ["evaluate_seconds", "prepare_seconds", "trace_seconds", "shade_seconds"]
        }
        frame = sum(med.values())
        ran = sorted({f"{f['accel']} {f['structure']}" for f in later})
        rows.append((label, ", ".join(ran), med, frame))
    auto_frame = rows[0][3] if rows and rows[0][0] == "auto" else None
    for label, ran, med, frame in rows:
        ratio = f"{frame / auto_frame:.2f}" if auto_frame else "—"
        print(
            f"| {label} | {ran} | {med['evaluate_seconds']:.1f} | {med['prepare_seconds']:.1f} | "
            f"{med['trace_seconds']:.1f} | {med['shade_seconds']:.1f} | {frame:.1f} | {ratio} |"
        )
    if auto_frame:
        rebuilt = [r for r in rows[1:] if "rebuilt" in r[0]]
        if rebuilt:
            best = min(rebuilt, key=lambda r: r[3])
            verdict = "met" if auto_frame < best[3] else "not met"
            print(
                f"\nauto {auto_frame:.1f} ms against the best rebuild ({best[0]}) "
                f"{best[3]:.1f} ms: {verdict}."
            )
    print()


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", choices=["shade", "frames"])
    ap.add_argument("--frames", default="0:2:0.25", help="START:END:STEP of the sequence")
    ap.add_argument("--threads", default="1,2", help="thread counts of the shading goal")
    ap.add_argument("--spp", type=int, default=4)
    ap.add_argument("--bounces", type=int, default=2)
    args = ap.parse_args()
    rayd = os.environ.get("RAYD", str(ROOT / "target" / "release" / "rayd"))
    has_embree = "embree" in subprocess.run(
        [rayd, "render", "--help"], capture_output=True, text=True
    ).stdout
    print(f"load average before: {os.getloadavg()[0]:.2f}\n")
    if args.only in (None, "shade"):
        shade_goal(rayd, [int(t) for t in args.threads.split(",")], (640, 480), args.spp, args.bounces)
    if args.only in (None, "frames"):
        frame_goal(rayd, 2, args.frames, has_embree)
    print(f"load average after: {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
