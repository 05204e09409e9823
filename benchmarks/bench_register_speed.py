"""rc's CPU and wall time, this tree against an older revision, side by side in one run.

Run (from the repository root, a git checkout)::

    python benchmarks/bench_register_speed.py --equivalence
    python benchmarks/bench_register_speed.py --old main --refit-parts --pairs weak-train --reps 11
    python benchmarks/bench_register_speed.py --size 2240 --presets default fast --threads 1 2 --reps 5
    git worktree add /tmp/rk-old a6e5868
    python benchmarks/bench_register_speed.py --fresh /tmp/rk-old --presets fast default --reps 5
    radiokit sim run --preset seed-breast -o /tmp/sb.h5
    python benchmarks/bench_register_speed.py --fresh /tmp/rk-old --process /tmp/sb.h5 --reps 2
    python benchmarks/bench_register_speed.py --fresh /tmp/rk-old --process /tmp/sb.h5 --files 4
    python benchmarks/bench_register_speed.py --straight --pairs weak family:0.006:1000 --threads 2 --reps 3

The older revision's (``--old``, default a6e5868, before session 5) ``radiokit/register/
_bspline.py`` and ``_common.py`` are loaded beside the current ones (the old module's
``@_method`` registrations undone), and ``radiokit.register.register(fixed, moving, "rc",
preset=...)`` runs with either ``rc`` (and det J of the quality assessment) in turn, old and
new interleaved, so a shared machine's load falls on both alike. ``RADIOKIT_THREADS``
and OpenCV's threads are set to ``--threads`` (as ``radiokit process`` sets them in a worker).

Timing prints, per preset and thread count, the medians over ``--reps`` of wall and CPU
(``time.process_time``: every thread of the process) seconds of the whole ``register`` call
(the method and the quality assessment) and of the method alone (wall), new / old, and the load
average before and after. ``--equivalence`` registers each pair once with each and prints the
median end-point error against the truth inside the body, old and new, and how far the two
fields are apart (median, 99th percentile and largest |difference|, px). ``--refit-parts`` times
the ``weak`` thinning refit's own work, old and new interleaved on the same inputs (the interior
thinning of both rounds from a first pass's field, and ``_noise_alpha``, which every pass runs):
the part of a whole run's difference that the optimiser's time, many times larger and noisier on a
shared machine, hides. ``--straight`` times ``auto-fast`` with and without going straight to
``weak-fast`` (``radiokit.register._auto.STRAIGHT_BINNING``, session 29) in one process, warm, and
compares the two fields (see :func:`straight`).

Pairs (``regdata``, test seeds): ``weak`` the family's weak texture (texture = noise = 0.01,
1/10-frame correlation length, 1 % motion; ``weak-train`` the same on TRAINING seed 1), ``rich`` ``analytic_pair`` (the texture ten times the
noise), ``weak1`` / ``weak1-train`` the family's texture at 1 % of the line integral (twice the noise;
TEST seed 1000 / TRAINING seed 1), ``phys`` the family's physically shaped motion (uniform expansion plus the lag around a
stiffer disc) on weak texture, ``camera`` scikit-image's camera under a local motion
(``bench_register_natural.py``'s test pair), ``astronaut`` scikit-image's astronaut under the
TRAINING local motion (``bench_register_natural.py --split train``: what a rich-texture time is
chosen on), ``retina`` / ``moon`` a TRAINING / TEST picture under the smooth motion (``sine``:
where ``auto``'s plain run stops and its finest level then runs on the weak field, session 27),
``family:TEXTURE:SEED`` the weak pair's case at another texture or seed, ``pva-phantom`` /
``seed-breast`` the simulated pairs (``regdata.sim_pair``, noisy; at the scene's own size).
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from regdata import Case, analytic_pair, family_pair


def make_pair(name, size):
    if name.startswith("family:"):  # family:TEXTURE:SEED, the weak pair's case at another texture or seed
        _, texture, seed = name.split(":")
        return family_pair(Case(size=size, texture=float(texture), noise=0.01, corr=0.1, seed=int(seed)))
    if name in ("pva-phantom", "seed-breast"):  # a simulated pair (noisy; simulated once, cached)
        from regdata import sim_pair

        return sim_pair(name, noisy=True)
    if name == "weak":
        return family_pair(Case(size=size, texture=0.01, noise=0.01, corr=0.1, seed=1000))
    if name == "weak-train":  # the same on a TRAINING seed (bench_register_weak2240.py's s1)
        return family_pair(Case(size=size, texture=0.01, noise=0.01, corr=0.1, seed=1))
    if name in ("weak1", "weak1-train"):  # texture 1 % of the line integral (twice the noise): weak settles
        return family_pair(Case(size=size, texture=0.02, noise=0.01, corr=0.1, seed=1000 if name == "weak1" else 1))
    if name in ("retina", "moon"):  # a picture under the smooth motion: auto's plain run stops (session 27)
        from bench_register_natural import natural

        return natural(name, size, "sine", "train" if name == "retina" else "test")
    if name == "rich":
        return analytic_pair(size, 0.01, 0.10, 0.01, seed=1)
    if name == "phys":
        return family_pair(Case(size=size, texture=0.01, noise=0.01, corr=0, motion="physical", seed=1001))
    if name == "camera":  # a natural image under a local motion (bench_register_natural.py, test)
        from bench_register_natural import natural

        return natural("camera", size, "local", "test")
    if name == "astronaut":  # the same on a TRAINING picture and motion
        from bench_register_natural import natural

        return natural("astronaut", size, "local", "train")
    raise ValueError(
        f"pair {name!r}: expected weak, weak-train, weak1, weak1-train, rich, phys, camera, astronaut, retina, moon, "
        "pva-phantom, seed-breast or family:TEXTURE:SEED"
    )


def _load(name, source):
    path = Path(tempfile.mkdtemp()) / f"{name}.py"
    path.write_text(source)
    spec = importlib.util.spec_from_file_location(f"radiokit.register.{name}", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _old_modules(rev):
    """``(old _bspline, old _common, old rc)``: revision ``rev``'s modules loaded beside ours, the
    methods they register over ours undone."""
    import radiokit.register as R

    R.load_methods()
    saved = dict(R.METHODS)
    root = Path(__file__).resolve().parent.parent
    src = {
        f: subprocess.run(
            ["git", "-C", str(root), "show", f"{rev}:radiokit/register/{f}.py"],
            capture_output=True,
            text=True,
            check=True,
        ).stdout
        for f in ("_bspline", "_common")
    }
    bspline_old = _load("_bspline_old", src["_bspline"])  # registers its methods over ours...
    rc_old = R.METHODS["rc"]
    R.METHODS.clear()
    R.METHODS.update(saved)  # ...undone
    return bspline_old, _load("_common_old", src["_common"]), rc_old


def methods(rev):
    """``{"old": (rc, det J), "new": (rc, det J)}``: of revision ``rev`` and of this tree."""
    import radiokit.register as R

    _, common_old, rc_old = _old_modules(rev)
    return {"old": (rc_old, common_old.jacobian_determinant), "new": (R.METHODS["rc"], R.jacobian_determinant)}


def refit_parts(rev, pair, size, reps, threads):
    """The thinning refit's own work (``weak``), old and new interleaved on the same inputs: the
    interior thinning of both rounds (``_interior_thinning``) on the field of a first pass, and
    the normalised pair's noise (``_noise_alpha``, run once per pass); medians of ``reps``, ms."""
    import radiokit.register._bspline as B

    set_threads(threads)
    old = _old_modules(rev)[0]
    fixed, moving, _, _ = make_pair(pair, size)
    d, _ = B._bspline_register(fixed, moving, None, preset="weak", refit_thinning=False, refit_again=0)
    side = B._fixed_side(fixed, None)  # measured once for both rounds, old and new alike
    f, m = B._normalise(fixed, moving)
    parts = {
        f"_interior_thinning {interior}": {
            k: (lambda mod=mod, interior=interior: mod._interior_thinning(fixed, moving, d, None, interior, side))
            for k, mod in (("old", old), ("new", B))
        }
        for interior in (B.REFIT_INTERIOR, B.REFIT_AGAIN_INTERIOR)
    }
    parts["_noise_alpha"] = {
        k: (lambda mod=mod: mod._noise_alpha(f, m, dict(noise_alpha=1.0))) for k, mod in (("old", old), ("new", B))
    }
    print(f"refit parts: {pair} {size} x {size}, {threads} thread(s), medians of {reps} interleaved runs, ms")
    print("| part | old | new | new - old |")
    print("|---|---|---|---|")
    for name, fns in parts.items():
        load0 = os.getloadavg()[0]
        for fn in fns.values():  # warm: caches, first touch
            fn()
        t = {k: [] for k in fns}
        for i in range(reps):
            for k in list(fns)[:: 1 if i % 2 == 0 else -1]:
                t0 = time.perf_counter()
                fns[k]()
                t[k].append(time.perf_counter() - t0)
        o, w = (1000 * float(np.median(t[k])) for k in ("old", "new"))
        print(f"| {name} | {o:.0f} | {w:.0f} | {w - o:+.0f} | load {load0:.1f}-{os.getloadavg()[0]:.1f}", flush=True)


def set_threads(n):
    import cv2

    os.environ["RADIOKIT_THREADS"] = str(n)
    cv2.setNumThreads(n)


def run(fn, fixed, moving, preset):
    """``(registration, wall s, cpu s)`` of ``register`` with ``fn`` = (rc, det J)."""
    import radiokit.register as R

    R.METHODS["rc"], R.jacobian_determinant = fn
    t0, c0 = time.perf_counter(), time.process_time()
    reg = R.register(fixed, moving, "rc", preset=preset)
    return reg, time.perf_counter() - t0, time.process_time() - c0


def same(a, b):
    """Field, confidence map and quality identical to the bit (but the time)?"""
    qa, qb = (dict(vars(x.quality), seconds=0.0) for x in (a, b))
    return bool(
        np.array_equal(a.displacement, b.displacement)
        and np.array_equal(a.confidence, b.confidence)
        and str(qa) == str(qb)
    )


def epe(d, truth, mask):
    return float(np.median(np.sqrt(((d - truth) ** 2).sum(axis=0))[mask]))


def equivalence(fns, pairs, sizes, presets, threads):
    set_threads(threads)
    print(
        f"equivalence, {threads} thread(s): median EPE (px) old / new; |new - old| field px: median, p99, max; "
        "field, confidence and quality identical to the bit"
    )
    for size in sizes:
        for name in pairs:
            fixed, moving, truth, mask = make_pair(name, size)
            for preset in presets:
                r = {k: run(fn, fixed, moving, preset)[0] for k, fn in fns.items()}
                diff = np.sqrt(((r["new"].displacement - r["old"].displacement) ** 2).sum(axis=0))[mask]
                eo, en = (epe(r[k].displacement, truth, mask) for k in ("old", "new"))
                print(
                    f"  {name} {size} {preset:9s} EPE {eo:.4f} / {en:.4f} (diff {en - eo:+.4f})  "
                    f"field diff {np.median(diff):.2e} {np.percentile(diff, 99):.2e} {diff.max():.2e}  "
                    f"ok {r['old'].quality.ok}/{r['new'].quality.ok} its {r['old'].quality.iterations}/"
                    f"{r['new'].quality.iterations} identical {same(r['old'], r['new'])}",
                    flush=True,
                )


def timing(fns, pair, size, presets, threads, reps):
    fixed, moving, _, _ = make_pair(pair, size)
    print(f"timing: {pair} {size} x {size}, medians of {reps} interleaved runs; new / old")
    print(
        "| preset | threads | wall old | wall new | cpu old | cpu new | method old | method new | cpu new/old | load |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|")
    for n in threads:
        set_threads(n)
        for preset in presets:
            for fn in fns.values():  # warm: the thread pool, imports, first-touch of the pair
                run(fn, fixed[:256, :256], moving[:256, :256], preset)
            load0 = os.getloadavg()[0]
            t = {k: [] for k in fns}
            for i in range(reps):
                for k in list(fns)[:: 1 if i % 2 == 0 else -1]:  # alternate who goes first
                    reg, wall, cpu = run(fns[k], fixed, moving, preset)
                    t[k].append((wall, cpu, reg.quality.seconds))
            m = {k: np.median(np.array(v), axis=0) for k, v in t.items()}
            o, w = m["old"], m["new"]
            print(
                f"| {preset} | {n} | {o[0]:.2f} | {w[0]:.2f} | {o[1]:.2f} | {w[1]:.2f} | {o[2]:.2f} | {w[2]:.2f} "
                f"| {w[1] / o[1]:.2f} | {load0:.1f}-{os.getloadavg()[0]:.1f} |",
                flush=True,
            )


_CHILD = """
import json, sys, time
sys.path.insert(0, sys.argv[1])
import numpy as np
f, m = np.load(sys.argv[2]), np.load(sys.argv[3])
import radiokit.register as R
R.load_methods()
t0, c0 = time.perf_counter(), time.process_time()
reg = R.register(f, m, "rc", preset=sys.argv[4])
print(json.dumps([time.perf_counter() - t0, time.process_time() - c0, reg.quality.seconds]))
"""


def fresh(old_tree, pair, size, presets, threads, reps):
    """Each run a new process (the first registration of a command-line run: imports done, the
    pair read from .npy files, memory not yet touched), old tree and this one alternately."""
    root = Path(__file__).resolve().parent.parent
    tmp = Path(tempfile.mkdtemp())
    fixed, moving, _, _ = make_pair(pair, size)
    np.save(tmp / "f.npy", fixed)
    np.save(tmp / "m.npy", moving)
    trees = {"old": str(Path(old_tree).resolve()), "new": str(root)}
    print(f"fresh processes: {pair} {size} x {size}, medians of {reps} alternating runs ({trees['old']} / this tree)")
    print(
        "| preset | threads | wall old | wall new | cpu old | cpu new | method old | method new | cpu new/old | load |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|")
    for n in threads:
        env = dict(os.environ, RADIOKIT_THREADS=str(n), OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1")
        for preset in presets:
            load0 = os.getloadavg()[0]
            t = {k: [] for k in trees}
            for i in range(reps):
                for k in list(trees)[:: 1 if i % 2 == 0 else -1]:
                    args = [sys.executable, "-c", _CHILD, trees[k], str(tmp / "f.npy"), str(tmp / "m.npy"), preset]
                    out = subprocess.run(args, env=env, capture_output=True, text=True, check=True).stdout
                    t[k].append(json.loads(out.strip().splitlines()[-1]))
            o, w = (np.median(np.array(t[k]), axis=0) for k in ("old", "new"))
            print(
                f"| {preset} | {n} | {o[0]:.2f} | {w[0]:.2f} | {o[1]:.2f} | {w[1]:.2f} | {o[2]:.2f} | {w[2]:.2f} "
                f"| {w[1] / o[1]:.2f} | {load0:.1f}-{os.getloadavg()[0]:.1f} |",
                flush=True,
            )


def straight(pairs, size, threads, reps):
    """``auto-fast`` as it is (``new``) and with ``_auto.STRAIGHT_BINNING`` out of reach (``old``:
    ``fast`` run first on every pair, as before session 29), in one process, interleaved, after a
    warm-up call of each on the pair: wall seconds (median and least of ``reps``), the preset
    returned, median EPE inside the body, and whether the two fields (and the confidence maps and
    every quality number but the time: :func:`same`) are identical to the bit."""
    import radiokit.register as R
    from radiokit.register import _auto

    set_threads(threads)
    line = _auto.STRAIGHT_BINNING
    print(f"auto-fast old (fast first) / new, warm, {threads} thread(s), {reps} interleaved calls each")
    print(
        "| pair | size | wall old (median, least) | wall new | old returns | new returns | EPE old | EPE new | field identical "
        "| field, map, quality identical |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|")
    for name in pairs:
        fixed, moving, truth, mask = make_pair(name, size)
        regs, t = {}, {"old": [], "new": []}
        try:
            for i in range(reps + 1):  # call 0 of each: the warm-up, not timed
                for k in ("old", "new") if i % 2 == 0 else ("new", "old"):
                    _auto.STRAIGHT_BINNING = line if k == "new" else 10**9
                    t0 = time.perf_counter()
                    regs[k] = R.register(fixed, moving, "rc", preset="auto-fast")
                    if i:
                        t[k].append(time.perf_counter() - t0)
        finally:
            _auto.STRAIGHT_BINNING = line
        o, n = regs["old"], regs["new"]
        wall = {k: f"{np.median(v):.2f}, {min(v):.2f}" for k, v in t.items()}
        print(
            f"| {name} | {fixed.shape[0]} | {wall['old']} | {wall['new']} | {o.options['auto'].preset} "
            f"| {n.options['auto'].preset} | {epe(o.displacement, truth, mask):.3f} | {epe(n.displacement, truth, mask):.3f} "
            f"| {np.array_equal(o.displacement, n.displacement)} | {same(o, n)} |",
            flush=True,
        )


def _numbers(obj, path=""):
    """``{path: value}`` of a results.json's numbers and strings, but times and paths."""
    if isinstance(obj, dict):
        out = {}
        for k, v in obj.items():
            if not any(w in k for w in ("second", "time", "path", "file", "date", "version", "host")):
                out.update(_numbers(v, f"{path}/{k}"))
        return out
    if isinstance(obj, list):
        return {k: v for i, x in enumerate(obj) for k, v in _numbers(x, f"{path}/{i}").items()}
    return {path: obj}


def process(old_tree, path, threads, reps):
    """``radiokit process FILE`` (default preset, one file) in new processes, old checkout and
    this tree alternately: wall, user and system seconds, and whether results.json agrees."""
    import resource

    root = Path(__file__).resolve().parent.parent
    trees = {"old": str(Path(old_tree).resolve()), "new": str(root)}
    out = Path(tempfile.mkdtemp())
    # the tree first on sys.path (a -c child has the working directory, maybe a checkout, before
    # PYTHONPATH)
    child = (
        "import sys; sys.path.insert(0, sys.argv.pop(1)); from radiokit.cli import main; sys.exit(main(sys.argv[1:]))"
    )
    print(f"radiokit process {path}: medians of {reps} alternating runs ({trees['old']} / this tree)")
    print("| threads | wall old | wall new | user+sys old | user+sys new | sys old | sys new | cpu new/old | load |")
    print("|---|---|---|---|---|---|---|---|---|")
    for n in threads:
        env = dict(os.environ, RADIOKIT_THREADS=str(n), OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1")
        load0 = os.getloadavg()[0]
        t = {k: [] for k in trees}
        for i in range(reps):
            for k in list(trees)[:: 1 if i % 2 == 0 else -1]:
                r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
                t0 = time.perf_counter()
                args = [
                    sys.executable,
                    "-c",
                    child,
                    trees[k],
                    "process",
                    str(path),
                    "-o",
                    str(out / k),
                    "--overwrite",
                    "-q",
                ]
                subprocess.run(args, env=env, check=True, capture_output=True)
                wall = time.perf_counter() - t0
                r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
                user, sys_ = r1.ru_utime - r0.ru_utime, r1.ru_stime - r0.ru_stime
                t[k].append((wall, user + sys_, sys_))
        o, w = (np.median(np.array(t[k]), axis=0) for k in ("old", "new"))
        print(
            f"| {n} | {o[0]:.1f} | {w[0]:.1f} | {o[1]:.1f} | {w[1]:.1f} | {o[2]:.1f} | {w[2]:.1f} | {w[1] / o[1]:.2f} "
            f"| {load0:.1f}-{os.getloadavg()[0]:.1f} |",
            flush=True,
        )
        res = {k: _numbers(json.loads(next((out / k).rglob("results.json")).read_text())) for k in trees}
        diff = sorted(k for k in res["old"].keys() | res["new"].keys() if res["old"].get(k) != res["new"].get(k))
        print(f"  results.json: {len(res['new'])} values, {len(diff)} differ {diff[:8]}", flush=True)


# bench_scaling's child, with the given tree's radiokit (and benchmarks) first on the path
_FILES_CHILD = """
import json, sys
sys.path.insert(0, sys.argv[1])
from benchmarks.bench_scaling import child_files
print(json.dumps(child_files(sys.argv[2], json.loads(sys.argv[3]), sys.argv[4], None)))
"""


def files(old_tree, path, n):
    """``n`` links to ``path`` processed one after the other in one process (two threads) and on
    a local Dask cluster of two workers (``bench_scaling``'s ``sequential`` and ``local-2``), old
    checkout and this tree: wall, user and system seconds and the ratio of the walls."""
    root = Path(__file__).resolve().parent.parent
    trees = {"old": str(Path(old_tree).resolve()), "new": str(root)}
    tmp = Path(tempfile.mkdtemp())
    paths = []
    for i in range(n):
        os.link(path, tmp / f"file{i}.h5")
        paths.append(str(tmp / f"file{i}.h5"))
    env = {k: v for k, v in os.environ.items() if k not in ("RADIOKIT_THREADS", "PYTHONPATH")}
    env.update(OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1")
    res = {}
    for mode, k in (("sequential", "old"), ("sequential", "new"), ("local-2", "new"), ("local-2", "old")):
        load0 = os.getloadavg()[0]
        out = tempfile.mkdtemp(dir=tmp)
        args = [sys.executable, "-c", _FILES_CHILD, trees[k], mode, json.dumps(paths), out]
        r = subprocess.run(args, env=env, capture_output=True, text=True, check=True)
        res[mode, k] = json.loads(r.stdout.strip().splitlines()[-1])
        print(f"  {mode:10s} {k}: {res[mode, k]}, load {load0:.1f}-{os.getloadavg()[0]:.1f}", flush=True)
    for k in trees:
        print(
            f"{k}: 2 workers / one after the other, wall {res['local-2', k]['wall_s'] / res['sequential', k]['wall_s']:.2f}"
        )


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--old", default="a6e5868", help="the older revision (git)")
    ap.add_argument("--equivalence", action="store_true", help="compare the results instead of timing")
    ap.add_argument("--pairs", nargs="+", default=["weak", "rich", "phys"])
    ap.add_argument("--sizes", nargs="+", type=int, default=[560, 2240], help="sizes of --equivalence")
    ap.add_argument("--size", type=int, default=2240, help="the timing's frame size (the weak pair)")
    ap.add_argument("--presets", nargs="+", default=["default", "fast", "weak-fast"])
    ap.add_argument("--threads", nargs="+", type=int, default=[1, 2])
    ap.add_argument("--reps", type=int, default=5)
    ap.add_argument("--refit-parts", action="store_true", help="time the thinning refit's own parts instead")
    ap.add_argument("--fresh", metavar="OLD_TREE", help="time new processes against a checkout of the old revision")
    ap.add_argument(
        "--straight", action="store_true", help="auto-fast with and without going straight to weak-fast, warm"
    )
    ap.add_argument("--process", metavar="FILE", help="with --fresh: time `radiokit process FILE` instead")
    ap.add_argument(
        "--files", type=int, default=0, help="with --process: N links of FILE, one after the other and on 2 workers"
    )
    a = ap.parse_args(argv)
    from threadpoolctl import threadpool_limits

    print(f"cores {os.cpu_count()}, load average {os.getloadavg()}")
    if a.fresh and a.process and a.files:
        files(a.fresh, a.process, a.files)
        return
    if a.fresh and a.process:
        process(a.fresh, a.process, a.threads, a.reps)
        return
    if a.straight:
        with threadpool_limits(limits=1, user_api="blas"):
            straight(a.pairs, a.size, a.threads[0], a.reps)
        print(f"load average {os.getloadavg()}")
        return
    if a.fresh:
        fresh(a.fresh, a.pairs[0], a.size, a.presets, a.threads, a.reps)
        return
    with threadpool_limits(limits=1, user_api="blas"):
        if a.refit_parts:
            refit_parts(a.old, a.pairs[0], a.size, a.reps, a.threads[0])
            return
    fns = methods(a.old)
    with threadpool_limits(limits=1, user_api="blas"):
        if a.equivalence:
            equivalence(fns, a.pairs, a.sizes, a.presets, a.threads[0])
        else:
            timing(fns, a.pairs[0], a.size, a.presets, a.threads, a.reps)
    print(f"load average {os.getloadavg()}")


if __name__ == "__main__":
    main()
