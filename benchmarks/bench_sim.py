"""Speed against accuracy of the finite-element phantom model, 3D against reduced (axisymmetric).

Run::

    python benchmarks/bench_sim.py [--full] [--quick] [--out out/bench_sim]

About 2 minutes (``--quick``: 20 s; ``--full`` adds the refined seed-breast mesh, about 6-8
minutes more). It prints a table and writes ``bench_sim.png`` and ``bench_sim.json``.

What it measures, side by side in one run (a shared 2-core machine: wall times are indicative,
the errors are exact):

1. A cylinder (40 mm high, 40 mm across) with a centred 10 mm sphere, 20/134 kPa neo-Hookean,
   compressed 25 %: the axisymmetric model at several mesh sizes and the 3D eighth model at two.
   The reference is the finest axisymmetric mesh; the error is the relative difference of the
   plate force and of the inclusion's chord change (15 -> 25 %, along the axis, from the
   projection).
2. ``seed-breast`` at the default mesh: the three states' time, plate force at 25 %, the
   inclusion chord change; with ``--full`` against a refined mesh (0.7 / 4.0 mm), the issue's
   convergence criterion (within 2 %).
3. One 2240 x 2240 projection of seed-breast at 25 %.

Targets: seed-breast three states <= 60 s, an axisymmetric scene <= 5 s, a projection <= 2 s;
with ``--full``, plate force and chord change within 2 % of the refined mesh.
"""
from __future__ import annotations

import argparse
import json
import time
from dataclasses import replace
from pathlib import Path

import numpy as np


def cylinder(model, size_inclusion, size_far):
    from sim.scene import Beam, Body, Inclusion, Material, MeshSpec, Scene

    gel = Material("gel", "neo-hookean", E_kpa=20.0, nu=0.495, attenuation_per_cm=0.77)
    stiff = Material("inclusion", "neo-hookean", E_kpa=134.0, nu=0.495, attenuation_per_cm=0.85)
    return Scene(name=f"cylinder-{model}", body=Body("cylinder", height_mm=40.0, diameter_mm=40.0, material=gel),
                 inclusions=[Inclusion("sphere", centre_mm=(0.0, 0.0, 0.0), diameter_mm=10.0, material=stiff)],
                 beam=Beam("parallel", "y"), mesh=MeshSpec(size_inclusion, size_far, model, True))


def chord_change(states, centre, extent_mm=12.0):
    """The inclusion's largest chord along the beam at the first state minus that at the last."""
    from sim.xray import Geometry, path_lengths

    px = 0.2
    n = int(extent_mm / px) | 1
    scene = states[0].solver.scene
    g = Geometry("parallel", scene.beam.direction, shape=(n, n), pixel_size_mm=px, centre_mm=centre)
    fem = states[0].solver.projection_mesh
    chords = [float(path_lengths(fem, g, s.displacement)[1].max()) for s in (states[0], states[-1])]
    return chords[0] - chords[-1]


def run(scene, ratios=(0.15, 0.25), centre=(0.0, 0.0, 0.0)):
    from sim.mechanics import compress

    t = time.perf_counter()
    states = compress(scene, ratios=ratios)
    seconds = time.perf_counter() - t
    return {"model": states[0].solver.fem.model, "size_inclusion_mm": scene.mesh.size_inclusion_mm,
            "size_far_mm": scene.mesh.size_far_mm, "dofs": int(states[0].solver.ndof), "seconds": seconds,
            "force_n": states[-1].plate_force_n, "chord_change_mm": chord_change(states, centre),
            "strain_ratio": states[-1].inclusion_strain / states[-1].background_strain}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--full", action="store_true", help="also the refined seed-breast mesh (minutes)")
    ap.add_argument("--quick", action="store_true", help="smallest sizes only (smoke run)")
    ap.add_argument("--out", type=Path, default=Path("out/bench_sim"))
    args = ap.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    from sim.scene import load_scene

    axi_sizes = [(2.0, 6.0), (1.0, 4.0)] if args.quick else [(2.0, 6.0), (1.0, 4.0), (0.5, 2.0), (0.35, 1.4)]
    d3_sizes = [(2.0, 6.0)] if args.quick else [(2.0, 6.0), (1.5, 5.0)]
    rows = []
    for s in axi_sizes:
        rows.append(dict(run(cylinder("axisymmetric", *s)), case="cylinder"))
    for s in d3_sizes:
        rows.append(dict(run(cylinder("3d", *s)), case="cylinder"))
    ref = min((r for r in rows if r["model"] == "axisymmetric"), key=lambda r: r["size_inclusion_mm"])
    for r in rows:
        r["force_error"] = abs(r["force_n"] / ref["force_n"] - 1)
        r["chord_error"] = abs(r["chord_change_mm"] / ref["chord_change_mm"] - 1)
    seed = []
    seed_sizes = [(1.0, 6.0)] + ([(0.7, 4.0)] if args.full else [])
    for s in seed_sizes:
        scene = load_scene("seed-breast")
        scene.mesh = replace(scene.mesh, size_inclusion_mm=s[0], size_far_mm=s[1])
        r = run(scene, ratios=(0.15, 0.20, 0.25), centre=(26.0, 0.0, 0.0))
        seed.append(dict(r, case="seed-breast"))
    if args.full:
        for r in seed:
            r["force_error"] = abs(r["force_n"] / seed[-1]["force_n"] - 1)
            r["chord_error"] = abs(r["chord_change_mm"] / seed[-1]["chord_change_mm"] - 1)

    # one full-size projection
    from sim.mechanics import compress
    from sim.xray import project

    scene = load_scene("seed-breast")
    state = compress(scene, ratios=(0.25,))[0]
    project(scene, state)  # builds and caches the surface
    times = []
    for _ in range(3):
        t = time.perf_counter()
        img = project(scene, state)
        times.append(time.perf_counter() - t)
    proj = {"shape": list(img.shape), "seconds": float(np.median(times))}

    print(f"{'case':<12} {'model':<13} {'sizes mm':>10} {'dofs':>7} {'time s':>8} {'F25 N':>10} "
          f"{'chord d mm':>11} {'F err':>8} {'chord err':>9}")
    for r in rows + seed:
        fe = f"{100 * r['force_error']:7.3f}%" if "force_error" in r else "      -"
        ce = f"{100 * r['chord_error']:8.3f}%" if "chord_error" in r else "       -"
        print(f"{r['case']:<12} {r['model']:<13} {r['size_inclusion_mm']:>4}/{r['size_far_mm']:<5} {r['dofs']:>7} "
              f"{r['seconds']:8.2f} {r['force_n']:10.5f} {r['chord_change_mm']:11.5f} {fe} {ce}")
    print(f"(cylinder errors against the finest axisymmetric mesh {ref['size_inclusion_mm']}/{ref['size_far_mm']} mm"
          + ("; seed-breast against 0.7/4.0 mm)" if args.full else ")"))
    axi_default = next(r for r in rows if r["model"] == "axisymmetric" and r["size_inclusion_mm"] == 1.0)
    checks = [("seed-breast 15/20/25 % at the default mesh <= 60 s", seed[0]["seconds"] <= 60, f"{seed[0]['seconds']:.1f} s"),
              ("axisymmetric scene (1.0/4.0 mm) <= 5 s", axi_default["seconds"] <= 5, f"{axi_default['seconds']:.2f} s"),
              ("one 2240 x 2240 projection <= 2 s", proj["seconds"] <= 2, f"{proj['seconds']:.2f} s")]
    if args.full:
        ok = seed[0]["force_error"] <= 0.02 and seed[0]["chord_error"] <= 0.02
        checks.append(("seed-breast default within 2 % of the refined mesh", ok,
                       f"force {100 * seed[0]['force_error']:.2f} %, chord change {100 * seed[0]['chord_error']:.2f} %"))
    for name, ok, value in checks:
        print(f"  {name}: {value} -> {'PASS' if ok else 'FAIL'}")

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 2, figsize=(12, 4.5))
    for model, marker in (("axisymmetric", "o"), ("3d", "s")):
        sel = [r for r in rows if r["model"] == model]
        ax[0].loglog([r["dofs"] for r in sel], [r["seconds"] for r in sel], marker + "-", label=f"cylinder, {model}")
        sel = [r for r in sel if r is not ref]
        ax[1].loglog([r["seconds"] for r in sel], [max(r["force_error"], 1e-6) for r in sel], marker + "-",
                     label=f"cylinder {model}: force")
        ax[1].loglog([r["seconds"] for r in sel], [max(r["chord_error"], 1e-6) for r in sel], marker + ":",
                     label=f"cylinder {model}: chord change")
    ax[0].loglog([r["dofs"] for r in seed], [r["seconds"] for r in seed], "^-", label="seed-breast, 3D quarter")
    if args.full:
        ax[1].loglog([seed[0]["seconds"]], [seed[0]["force_error"]], "^", label="seed-breast default: force")
    ax[0].set_xlabel("displacement unknowns")
    ax[0].set_ylabel("time for the compression series (s)")
    ax[0].set_title("cost against mesh size")
    ax[1].axhline(0.02, color="grey", lw=0.8, ls="--")
    ax[1].set_xlabel("time (s)")
    ax[1].set_ylabel("relative error against the finest mesh")
    ax[1].set_title("accuracy against time")
    for a in ax:
        a.grid(True, which="both", alpha=0.3)
        a.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(args.out / "bench_sim.png", dpi=110)
    (args.out / "bench_sim.json").write_text(json.dumps({"cylinder": rows, "seed_breast": seed, "projection": proj,
                                                          "checks": [[n, bool(o), v] for n, o, v in checks]}, indent=1))
    print(f"chart {args.out / 'bench_sim.png'}")
    return 0 if all(ok for _, ok, _ in checks) else 1


if __name__ == "__main__":
    raise SystemExit(main())
