"""Benchmark: how the cost of every stage grows with the work, and what Dask workers buy.

Run (about 15 minutes on a 2-core machine; ``--quick`` about 4)::

    python benchmarks/bench_scaling.py [--quick] [--sections files,frame,mesh,steps,memory]
                                       [--repeats 2] [--out out/bench_scaling]

Every measurement runs in a fresh subprocess (``--_child``), so that its peak memory is its own:
the child's ``VmHWM`` from ``/proc/self/status``, reset between the stages of one child by
writing 5 to ``/proc/self/clear_refs`` (Linux), so each stage's peak is its own too. Where two
set-ups are compared their runs are interleaved in a shuffled order, ``--repeats`` times, and the
medians are reported: the noise of a shared machine hits both alike.

Sections
--------
files   ``radiokit process`` on ``--files`` simulated 560 x 560 experiments (copies of one file):
        one after the other in one process (``process`` in a loop), and through Dask
        (``process_many``) on a local cluster of 1 and 2 workers, and on a ``dask scheduler``
        with two ``dask worker --nthreads 1`` processes started from the command line. Wall
        time, and user and system CPU time of every process involved. Targets: 2 workers
        <= 0.6x the sequential time; system time < 10 % of user time.
frame   the stages against the frame size (560, 1120, 2240 from the seed-breast scene at
        binning 4, 2, 1): simulation (mechanics, projection, truth, frames) and processing
        (read, calibrate, correct, register one pair, enhance + measure, report).
mesh    mechanics (3 states) against the mesh's dofs: seed-breast's element sizes scaled by
        1.6, 1.25, 1 and 0.8; the plate force of each against the finest, the mesh's convergence.
steps   mechanics against the number of compression states (2, 3, 5, 8 up to 25 %).
truth   the truth of seed-breast's three pairs at 2240 x 2240: the fast path against the reference
        evaluation (``truth_displacement(..., _reference=True)``), interleaved; the largest difference.
memory  peak memory of ``radiokit process`` on a 10-frame and a 100-frame experiment file
        (1120 x 1120 synthetic frames: 10 darks, 10 flats, 80 projections against 2, 2, 6).
        Target: the 100-frame peak within 20 % of the 10-frame one.

Exponents: a least-squares line through log(time) against log(size) per stage. Writes
``scaling.json`` and ``scaling.png`` into ``--out``.
"""

from __future__ import annotations

import argparse
import json
import os
import random
import resource
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
MiB = 2**20


# -- measuring inside a child ------------------------------------------------------------------
def _vmhwm() -> int:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) * 1024
    return 0


def _reset_peak():
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
    except OSError:  # not Linux, or not allowed: the peaks are then cumulative
        pass


class _Stages:
    """Time and peak memory of each stage run inside ``with stages("name"):``."""

    def __init__(self):
        self.seconds, self.peak = {}, {}

    def __call__(self, name):
        stages = self

        class _Stage:
            def __enter__(self):
                _reset_peak()
                self.t = time.perf_counter()

            def __exit__(self, *exc):
                stages.seconds[name] = time.perf_counter() - self.t
                stages.peak[name] = _vmhwm()

        return _Stage()


def child_sim(binning: int, out: str) -> dict:
    from sim.lab import simulate_experiment
    from sim.scene import load_scene, with_binning

    # binned at a lower current (the same counts per read-out pixel): the same source binned would clip
    scene = with_binning(load_scene("seed-breast"), binning)
    _reset_peak()
    res = simulate_experiment(scene, out, overwrite=True, progress=False)
    return {"seconds": res["seconds"], "peak_bytes": _vmhwm(), "shape": res["frame_shape"]}


def child_process(path: str, out_dir: str) -> dict:
    """The processing stages of one file, each timed with its own peak memory."""
    from radiokit.calibrate import Calibration
    from radiokit.io import open_frames
    from radiokit.pipeline import Config, _load_steps, process
    from radiokit.register import register

    st = _Stages()
    with st("read"), open_frames(path) as src:
        for i in range(len(src)):
            src[i]
    with st("calibrate"):
        Calibration.from_experiment(path)
    with st("correct"):  # calibrates again (its own time is subtracted below)
        steps, _, _, _, t = _load_steps(path, False)
    st.seconds["correct"] = t["correct_s"]
    with st("register"):  # the paper's pair, rc, whole frame
        register(steps[-1], steps[-2], "rc")
    with st("process"):
        res = process(path, Config(progress=False), out_dir=out_dir)
    tm = res.results["timings"]
    st.seconds["enhance_measure"] = tm["enhance_s"] + tm["measure_s"]
    st.seconds["report"] = tm.get("report_s", float("nan"))
    return {"seconds": st.seconds, "peak_bytes": st.peak, "process_timings": tm}


def child_mechanics(scale: float, n_states: int) -> dict:
    from sim.mechanics import compress
    from sim.scene import load_scene

    scene = load_scene("seed-breast")
    scene.mesh.size_inclusion_mm *= scale
    scene.mesh.size_far_mm *= scale
    ratios = tuple(np.linspace(0.25 / n_states, 0.25, n_states).round(4)) if n_states != 3 else None
    _reset_peak()
    t = time.perf_counter()
    states = compress(scene, ratios)
    s = states[0].solver
    return {
        "seconds": time.perf_counter() - t,
        "peak_bytes": _vmhwm(),
        "dofs": int(s.ndof),
        "factorisations": s.factorisations,
        "krylov_iterations": s.krylov_iterations,
        "plate_force_n": [st.plate_force_n for st in states],
        "ratios": [st.ratio for st in states],
    }


def child_truth(repeats: int) -> dict:
    """Truth for seed-breast's three pairs at 2240 x 2240: the fast path against the reference
    evaluation, interleaved; and their largest difference."""
    from sim.lab import body_footprint, project_state
    from sim.mechanics import compress
    from sim.scene import load_scene
    from sim.truth import truth_displacement

    scene = load_scene("seed-breast")
    scene.detector.binning = 1
    states = compress(scene)
    bodies = [body_footprint(scene, project_state(scene, states[0].solver, s.displacement)[0]) for s in states]
    pairs = [(a, b) for b in range(len(states)) for a in range(b)]
    times = {"fast": [], "reference": []}
    diff = 0.0
    for _ in range(repeats):
        for name in random.sample(list(times), 2):
            t = time.perf_counter()
            fields = [
                truth_displacement(scene, states[b], states[a], body=bodies[b], _reference=name == "reference")
                for a, b in pairs
            ]
            times[name].append(time.perf_counter() - t)
            if name == "fast":
                fast = fields
            else:
                ref = fields
        diff = max(float(np.abs(f - r).max()) for f, r in zip(fast, ref))
    med = {k: statistics.median(v) for k, v in times.items()}
    return {
        "seconds": med,
        "runs": times,
        "ratio": med["fast"] / med["reference"],
        "max_diff_px": diff,
        "pairs": len(pairs),
    }


def child_files(mode: str, paths: list, out_root: str, scheduler: str | None) -> dict:
    from radiokit.pipeline import Config, process, process_many

    cfg = Config(progress=False)
    t = time.perf_counter()
    if mode == "sequential":
        for p in paths:
            process(p, cfg, out_dir=Path(out_root) / Path(p).stem)
    else:
        workers = int(mode.split("-")[-1]) if mode.startswith("local") else None
        res = process_many(paths, cfg, out_root=out_root, workers=workers, scheduler=scheduler)
        bad = [r for r in res if "error" in r]
        if bad:
            raise RuntimeError(bad[0]["error"])
    wall = time.perf_counter() - t
    me, kids = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return {"wall_s": wall, "user_s": me.ru_utime + kids.ru_utime, "sys_s": me.ru_stime + kids.ru_stime}


def child_memory(path: str, out_dir: str) -> dict:
    from radiokit.cli import main

    _reset_peak()
    code = main(
        [
            "process",
            path,
            "-o",
            out_dir,
            "-q",
            "--no-report",
            "--inclusion",
            *map(str, _SYN_INC),
            "--background",
            *map(str, _SYN_BG),
            "--crop-mm",
            "0",
        ]
    )
    return {"code": code, "peak_bytes": _vmhwm()}


# -- running children --------------------------------------------------------------------------
def run_child(kind: str, *args) -> dict:
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    cmd = [sys.executable, str(Path(__file__).resolve()), "--_child", kind, json.dumps(list(args))]
    out = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=ROOT)
    if out.returncode != 0:
        raise RuntimeError(f"child {kind} {args} failed:\n{out.stderr[-3000:]}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def _cpu_of_tree(procs) -> tuple[float, float]:
    import psutil

    user = sys_ = 0.0
    for p in procs:
        try:
            for q in [p] + p.children(recursive=True):
                c = q.cpu_times()
                user += c.user + c.children_user
                sys_ += c.system + c.children_system
        except psutil.NoSuchProcess:
            pass
    return user, sys_


def run_files_on_scheduler(paths, out_root, tmp) -> dict:
    """``dask scheduler`` and two ``dask worker --nthreads 1`` started as a user starts them;
    their CPU time is read from the process trees before they are stopped."""
    import psutil

    bin_dir = Path(sys.executable).parent
    sched_file = Path(tmp) / "scheduler.json"
    sched_file.unlink(missing_ok=True)
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    logs = open(Path(tmp) / "dask.log", "w")
    sched = subprocess.Popen(
        [str(bin_dir / "dask"), "scheduler", "--scheduler-file", str(sched_file), "--port", "0", "--no-dashboard"],
        stdout=logs,
        stderr=logs,
        env=env,
    )
    for _ in range(300):
        if sched_file.exists():
            break
        time.sleep(0.1)
    workers = subprocess.Popen(
        [
            str(bin_dir / "dask"),
            "worker",
            "--scheduler-file",
            str(sched_file),
            "--nworkers",
            "2",
            "--nthreads",
            "1",
            "--no-dashboard",
        ],
        stdout=logs,
        stderr=logs,
        env=env,
    )
    procs = [psutil.Process(sched.pid), psutil.Process(workers.pid)]
    try:
        address = json.loads(sched_file.read_text())["address"]
        from dask.distributed import Client

        with Client(address) as c:
            c.wait_for_workers(2, timeout=120)
        u0, s0 = _cpu_of_tree(procs)
        r = run_child("files", "scheduler-2", paths, out_root, address)
        u1, s1 = _cpu_of_tree(procs)
        return {"wall_s": r["wall_s"], "user_s": r["user_s"] + u1 - u0, "sys_s": r["sys_s"] + s1 - s0}
    finally:
        for p in (workers, sched):
            p.terminate()
            try:
                p.wait(timeout=30)
            except subprocess.TimeoutExpired:
                p.kill()
        logs.close()


# -- sections ----------------------------------------------------------------------------------
def section_files(base: Path, n_files: int, repeats: int, source: Path) -> dict:
    paths = []
    for i in range(n_files):
        p = base / f"file{i}.h5"
        shutil.copy(source, p)
        paths.append(str(p))
    # the copies' dirty pages would otherwise be written back during the first mode's run (measured:
    # the first of four modes 75.7 s, the same mode again 66-68 s)
    os.sync()
    modes = ["sequential", "local-1", "local-2", "scheduler-2"]
    runs = {m: [] for m in modes}
    rng = random.Random(0)
    for _ in range(repeats):
        order = modes[:]
        rng.shuffle(order)
        for m in order:
            out_root = base / f"out-{m}"
            shutil.rmtree(out_root, ignore_errors=True)
            r = (
                run_files_on_scheduler(paths, str(out_root), str(base))
                if m.startswith("scheduler")
                else run_child("files", m, paths, str(out_root), None)
            )
            runs[m].append(r)
            print(
                f"  files: {m:12s} wall {r['wall_s']:6.1f} s, user {r['user_s']:6.1f} s, sys {r['sys_s']:5.1f} s",
                flush=True,
            )
    med = {m: {k: statistics.median(r[k] for r in rs) for k in ("wall_s", "user_s", "sys_s")} for m, rs in runs.items()}
    seq = med["sequential"]["wall_s"]
    ratio = {m: med[m]["wall_s"] / seq for m in modes}
    sys_share = {m: med[m]["sys_s"] / med[m]["user_s"] for m in modes}
    return {
        "n_files": n_files,
        "runs": runs,
        "median": med,
        "wall_over_sequential": ratio,
        "sys_over_user": sys_share,
        "pass": all(ratio[m] <= 0.6 for m in ("local-2", "scheduler-2")) and all(v < 0.1 for v in sys_share.values()),
    }


def section_frame(base: Path, binnings) -> dict:
    out = {}
    for b in binnings:
        path = base / f"sim-b{b}.h5"
        sim = run_child("sim", b, str(path))
        proc = run_child("process", str(path), str(base / f"out-b{b}"))
        side = sim["shape"][0]
        out[side] = {"sim": sim, "process": proc}
        sec = {**{k: v for k, v in sim["seconds"].items() if k != "total"}, **proc["seconds"]}
        print(f"  frame {side}: " + ", ".join(f"{k} {v:.2f} s" for k, v in sec.items()), flush=True)
    return out


def section_mesh(scales) -> dict:
    out = {}
    for s in scales:
        r = run_child("mechanics", s, 3)
        out[s] = r
        print(
            f"  mesh x{s}: {r['dofs']} dofs, {r['seconds']:.1f} s, peak {r['peak_bytes'] / MiB:.0f} MiB, "
            f"force {r['plate_force_n'][-1]:.4f} N",
            flush=True,
        )
    finest = out[min(scales)]["plate_force_n"]
    for r in out.values():
        r["force_error_vs_finest"] = max(abs(a / b - 1) for a, b in zip(r["plate_force_n"], finest))
    return out


def section_steps(counts, scale) -> dict:
    out = {}
    for n in counts:
        r = run_child("mechanics", scale, n)
        out[n] = r
        print(f"  steps {n}: {r['seconds']:.1f} s", flush=True)
    return out


# the synthetic memory experiment: a slab thinned by compression with a denser square
_SYN_SIDE = 1120
_SYN_INC = (500, 620, 500, 620)
_SYN_BG = (500, 620, 250, 370)


def write_synthetic(path: Path, n_cal: int, per_step: int):
    from radiokit.io import ExperimentWriter, ImageKey

    rng = np.random.default_rng(0)
    n = _SYN_SIDE
    rr, cc = np.mgrid[0:n, 0:n]
    sq = (np.abs(rr - 560) < 60) & (np.abs(cc - 560) < 60)
    with ExperimentWriter(path, shape=(n, n), overwrite=True, pixel_size_mm=0.05) as w:
        for _ in range(n_cal):
            w.append((100 + rng.normal(0, 2, (n, n))).astype(np.uint16), image_key=ImageKey.DARK)
        for _ in range(n_cal):
            w.append((3100 + rng.normal(0, 50, (n, n))).astype(np.uint16), image_key=ImageKey.FLAT)
        for step, (tb, ti) in enumerate([(20.0, 8.0), (18.0, 7.8), (16.0, 7.6)], start=1):
            L = 0.08 * tb + 0.03 * ti * sq
            clean = 100 + 3000 * np.exp(-L)
            for _ in range(per_step[step - 1] if isinstance(per_step, tuple) else per_step):
                w.append(
                    (clean + rng.normal(0, 20, (n, n))).astype(np.uint16),
                    image_key=ImageKey.PROJECTION,
                    step=step,
                    ratio=0.1 * step,
                )


def section_memory(base: Path, repeats: int) -> dict:
    files = {10: base / "mem10.h5", 100: base / "mem100.h5"}
    write_synthetic(files[10], 2, 2)
    write_synthetic(files[100], 10, (27, 27, 26))
    runs = {k: [] for k in files}
    for _ in range(repeats):
        for k, p in files.items():
            r = run_child("memory", str(p), str(base / f"mem-out-{k}"))
            runs[k].append(r["peak_bytes"])
            print(f"  memory: {k:3d}-frame file, peak {r['peak_bytes'] / MiB:.0f} MiB", flush=True)
    peak = {k: statistics.median(v) for k, v in runs.items()}
    return {
        "side": _SYN_SIDE,
        "peak_bytes": peak,
        "runs": runs,
        "ratio": peak[100] / peak[10],
        "pass": peak[100] <= 1.2 * peak[10],
    }


# -- exponents and the chart -------------------------------------------------------------------
def exponent(xs, ys) -> float:
    xs, ys = np.asarray(xs, float), np.asarray(ys, float)
    ok = (xs > 0) & (ys > 0) & np.isfinite(ys)
    if ok.sum() < 2:
        return float("nan")
    return float(np.polyfit(np.log(xs[ok]), np.log(ys[ok]), 1)[0])


def fit(result) -> dict:
    ex = {}
    fr = result.get("frame")
    if fr:
        sides = sorted(fr, key=float)
        px = [float(s) ** 2 for s in sides]
        stages = {
            **{k: [fr[s]["sim"]["seconds"][k] for s in sides] for k in ("projection", "truth", "frames")},
            **{
                k: [fr[s]["process"]["seconds"][k] for s in sides]
                for k in ("read", "calibrate", "correct", "register", "enhance_measure", "report")
            },
        }
        ex["time_vs_pixels"] = {k: exponent(px, v) for k, v in stages.items()}
        peaks = {k: [fr[s]["process"]["peak_bytes"][k] for s in sides] for k in fr[sides[0]]["process"]["peak_bytes"]}
        ex["peak_memory_vs_pixels"] = {k: exponent(px, v) for k, v in peaks.items()}
    if result.get("mesh"):
        m = result["mesh"]
        ex["mechanics_time_vs_dofs"] = exponent([r["dofs"] for r in m.values()], [r["seconds"] for r in m.values()])
        ex["mechanics_memory_vs_dofs"] = exponent(
            [r["dofs"] for r in m.values()], [r["peak_bytes"] for r in m.values()]
        )
    if result.get("steps"):
        s = result["steps"]
        ex["mechanics_time_vs_states"] = exponent([float(k) for k in s], [r["seconds"] for r in s.values()])
    if result.get("files"):
        f = result["files"]["median"]
        ex["files_speedup_2_workers_local"] = f["sequential"]["wall_s"] / f["local-2"]["wall_s"]
    return ex


def chart(result, path: Path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 4, figsize=(18, 4.2))
    fr = result.get("frame")
    if fr:
        sides = sorted(fr, key=float)
        px = np.array([float(s) ** 2 for s in sides]) / 1e6
        for k in ("projection", "truth", "frames"):
            axes[0].loglog(px, [fr[s]["sim"]["seconds"][k] for s in sides], "o--", label=f"sim {k}")
        for k in ("read", "calibrate", "correct", "register", "enhance_measure", "report"):
            axes[0].loglog(px, [fr[s]["process"]["seconds"][k] for s in sides], "o-", label=k)
        axes[0].set(xlabel="frame (Mpx)", ylabel="s", title="stage time vs frame size")
        axes[0].legend(fontsize=7)
        for k in fr[sides[0]]["process"]["peak_bytes"]:
            axes[1].loglog(px, [fr[s]["process"]["peak_bytes"][k] / MiB for s in sides], "o-", label=k)
        axes[1].set(xlabel="frame (Mpx)", ylabel="peak RSS (MiB)", title="stage peak memory vs frame size")
        axes[1].legend(fontsize=7)
    if result.get("mesh"):
        m = result["mesh"].values()
        axes[2].loglog([r["dofs"] for r in m], [r["seconds"] for r in m], "o-", label="mechanics, 3 states")
        if result.get("steps"):
            ax2 = axes[2].twiny()
            s = result["steps"]
            ax2.plot([float(k) for k in s], [r["seconds"] for r in s.values()], "s--", color="C3", label="vs states")
            ax2.set_xlabel("states (coarse mesh)", color="C3")
        axes[2].set(xlabel="dofs", ylabel="s", title="mechanics")
        axes[2].legend(fontsize=7)
    if result.get("files"):
        f = result["files"]["median"]
        names = list(f)
        axes[3].bar(names, [f[n]["user_s"] for n in names], label="user")
        axes[3].bar(names, [f[n]["sys_s"] for n in names], bottom=[f[n]["user_s"] for n in names], label="system")
        axes[3].plot(names, [f[n]["wall_s"] for n in names], "ko-", label="wall")
        axes[3].set(ylabel="s", title=f"{result['files']['n_files']} files at 560 x 560")
        axes[3].legend(fontsize=7)
        axes[3].tick_params(axis="x", labelsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--sections", default="files,frame,mesh,steps,memory,truth")
    p.add_argument("--quick", action="store_true", help="smaller sweeps (frames 560 and 1120, two meshes)")
    p.add_argument("--repeats", type=int, default=2, help="interleaved repetitions where set-ups are compared")
    p.add_argument("--files", type=int, default=4, help="experiment files in the files section (default 4)")
    p.add_argument("--out", type=Path, default=ROOT / "out" / "bench_scaling")
    p.add_argument("--_child", nargs=2, help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args._child:
        kind, rest = args._child[0], json.loads(args._child[1])
        fn = {
            "sim": child_sim,
            "process": child_process,
            "mechanics": child_mechanics,
            "files": child_files,
            "memory": child_memory,
            "truth": child_truth,
        }[kind]
        print(json.dumps(fn(*rest)))
        return 0

    sections = args.sections.split(",")
    args.out.mkdir(parents=True, exist_ok=True)
    base = Path(tempfile.mkdtemp(prefix="radiokit-scaling-"))
    load = os.getloadavg()
    result = {"cpus": os.cpu_count(), "load_average_before": load, "quick": args.quick}
    print(
        f"{os.cpu_count()} CPUs, load average {load[0]:.2f} before the run (a shared machine inflates every "
        "absolute number; ratios are measured side by side)"
    )
    t0 = time.perf_counter()
    try:
        if "files" in sections or "frame" in sections:
            small = base / "sim-b4.h5"
            print("simulating the 560 x 560 experiment ...", flush=True)
            run_child("sim", 4, str(small))
        if "files" in sections:
            result["files"] = section_files(base, args.files, args.repeats, small)
        if "frame" in sections:
            result["frame"] = section_frame(base, (4, 2) if args.quick else (4, 2, 1))
        if "mesh" in sections:
            result["mesh"] = section_mesh((1.6, 1.0) if args.quick else (1.6, 1.25, 1.0, 0.8))
        if "steps" in sections:
            result["steps"] = section_steps((2, 3, 5) if args.quick else (2, 3, 5, 8), 1.6)
        if "memory" in sections:
            result["memory"] = section_memory(base, 1 if args.quick else args.repeats)
        if "truth" in sections:
            t = result["truth"] = run_child("truth", max(args.repeats, 1))
            print(
                f"  truth, {t['pairs']} pairs at 2240 x 2240: fast {t['seconds']['fast']:.1f} s, reference "
                f"{t['seconds']['reference']:.1f} s -> {t['ratio']:.2f}x; largest difference {t['max_diff_px']:.2g} px"
            )
    finally:
        shutil.rmtree(base, ignore_errors=True)
    result["exponents"] = fit(result)
    result["seconds"] = time.perf_counter() - t0
    (args.out / "scaling.json").write_text(json.dumps(result, indent=1, default=str))
    chart(result, args.out / "scaling.png")
    print(json.dumps(result["exponents"], indent=1))
    if "files" in result:
        f = result["files"]
        print(
            "files: "
            + ", ".join(
                f"{m} {r:.2f}x sequential (sys/user {f['sys_over_user'][m]:.3f})"
                for m, r in f["wall_over_sequential"].items()
            )
            + f" -> {'PASS' if f['pass'] else 'FAIL'}"
        )
    if "memory" in result:
        m = result["memory"]
        print(f"memory: 100-frame peak / 10-frame peak = {m['ratio']:.3f} -> {'PASS' if m['pass'] else 'FAIL'}")
    print(f"wrote {args.out / 'scaling.json'} and {args.out / 'scaling.png'} in {result['seconds']:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
