"""``radiokit demo``: the whole system on the virtual bench, hardware emulated, in a few minutes.

1. The compression-series protocol runs against the L8121 emulator on a pseudo-terminal (through
   the real pyserial stack: warm-up, darks, flats, three compression steps, tube off), a
   ``SimDetector`` and a ``SimFrame`` on a finite-element scene (``seed-breast`` by default).
2. The same protocol runs on a control scene: the same geometry and attenuation, the inclusion as
   soft as the background -- what compression alone does, without elasticity contrast.
3. ``radiokit.pipeline.process`` calibrates, corrects, registers, enhances (k = 1, 2), measures
   both, compares with the truth the simulation stored, and writes the report.
4. The headline table is printed with the report's path.
"""

from __future__ import annotations

import argparse
import dataclasses
import shlex
import sys
import time
from pathlib import Path

__all__ = ["run_demo", "add_demo"]


def _exposure(scene, kv_min=40.0):
    """The source setting for a scene: its kV, raised to the L8121's 40 kV floor if lower (the
    seed-breast scene is a 28 kV mammogram), with the current lowered to keep the panel's open-beam
    signal where the scene puts it (signal ~ uA kV^2 in the panel model). A binned demo's scene
    already has its current lowered by the binning squared (:func:`sim.scene.with_binning`)."""
    kv = max(float(scene.exposure.voltage_kv), kv_min)
    ua = float(scene.exposure.current_ua) * (float(scene.exposure.voltage_kv) / kv) ** 2
    return kv, round(ua)


def _protocol(scene, output, *, initial_height_mm, frames_per_step, darks, flats, warm, dialect="A"):
    from acquisition.protocols import load_protocol

    kv, ua = _exposure(scene)
    return load_protocol(
        {
            "output": str(output),
            "name": "demo",
            "source": {"voltage_kv": kv, "current_ua": ua, "poll_s": 0.25, "dialect": dialect},
            "detector": {"kind": "sim"},
            "frame": {"kind": "sim", "initial_height_mm": initial_height_mm},
            "series": {
                "darks": darks,
                "flats": flats,
                "frames_per_step": frames_per_step,
                "steps": [0.15, 0.20, 0.25],
                "settle_s": 0.0,
            },
            "sim": {"scene": scene.to_toml(), "warmup_s": 2.0, "ramp_s": 0.3, "warmed_up": warm},
        }
    )


#: the files and folders a demo makes in its folder, and nothing else
_DEMO_OUTPUTS = ("experiment.h5", "experiment.log", "control.h5", "control.log", "results")


def _demo_folder(out_dir, overwrite) -> Path:
    """Claim ``out_dir`` for the demo: refuse a folder radiokit did not make; with ``overwrite``
    remove a previous demo's own outputs (and only those)."""
    import shutil

    from radiokit.io import RESULTS_MARKER, check_output, folder_marker

    # a results folder of `radiokit process` is refused there, --overwrite or not: the demo wrote
    # its marker over that folder's list of files and ran beside its report, one folder mixing two runs
    out = check_output(out_dir, overwrite=overwrite, folder=True, made_by="demo")
    out.mkdir(parents=True, exist_ok=True)
    for name in _DEMO_OUTPUTS:
        old = out / name
        if old.is_dir() and not old.is_symlink():
            shutil.rmtree(old)
        elif old.exists() or old.is_symlink():
            old.unlink()
    (out / RESULTS_MARKER).write_text(folder_marker("demo") + "\n")
    return out


def control_scene(scene):
    """The same scene with every inclusion's stiffness set to the background's (attenuation kept)."""
    body_mat = scene.body.material
    incs = [
        dataclasses.replace(
            inc,
            material=dataclasses.replace(
                body_mat,
                name=f"{inc.material.name} as soft as the background",
                attenuation_per_cm=inc.material.attenuation_per_cm,
            ),
        )
        for inc in scene.inclusions
    ]
    return dataclasses.replace(scene, name=f"{scene.name}-control", inclusions=incs)


def _checked_config(out_dir, frames_per_step, method, register_preset, binning, n_calibration, progress):
    """The pipeline's configuration, and the arguments checked before the folder is claimed: a bad
    ``--frames`` left the claimed folder behind, a bad ``--method`` was found only after both
    acquisitions, and a huge ``--frames`` started terabytes of frames."""
    from radiokit.io import check_free_space
    from radiokit.pipeline import Config
    from radiokit.register import BSPLINE_METHODS

    if int(frames_per_step) != frames_per_step or frames_per_step < 1:
        raise ValueError(f"--frames {frames_per_step}: expected a whole number of frames per step, at least 1")
    if method not in BSPLINE_METHODS:  # the demo runs the pipeline's presets, which are theirs
        raise ValueError(f"--method {method}: the demo registers with a B-spline method: {', '.join(BSPLINE_METHODS)}")
    cfg = Config(
        control=str(Path(out_dir) / "control.h5"),
        progress=progress,
        method=method,
        register_options={"preset": register_preset},
    )
    side = 2240 // (int(binning) if binning else 1)  # uint16 frames of both series (three steps each)
    check_free_space(Path(out_dir) / "experiment.h5", 2 * side**2 * 2 * (n_calibration + frames_per_step * 3))
    return cfg


def run_demo(
    out_dir="out/demo",
    *,
    preset="seed-breast",
    binning=None,
    frames_per_step=2,
    darks=10,
    flats=10,
    coarse=False,
    method="rc",
    register_preset="auto",
    progress=True,
    dialect="A",
    overwrite=False,
    view=None,
    imaging=None,
) -> dict:
    """Run the demo (see the module docstring); returns the headline numbers and paths.

    The lab's settings by default: the full panel (``binning`` 1), the scene's own mesh, the
    pipeline's registration preset (``auto``); ``binning=2`` (at a quarter of the tube current, as
    the lab bins: the same counts per read-out pixel, a quarter of the dose), ``coarse=True`` and
    ``register_preset="auto-fast"`` are the cheaper ones. ``dialect`` ("A" or "B") is the L8121 command dialect the emulator and
    the driver speak. ``out_dir`` must be new, empty, or a previous demo's folder (replaced only
    with ``overwrite=True``): the demo never deletes a file it did not make. ``view`` is the beam
    direction (``"through_plates"`` or ``"side"``; default: the preset's own), ``imaging`` the
    imaging model (``"paper"`` or ``"experiment"``; default: the preset's, ``sim.scene.Imaging``)."""
    from acquisition.protocols import run, sim_devices
    from radiokit.pipeline import process
    from sim.bench import VirtualBench
    from sim.scene import load_scene, with_binning

    t0 = time.perf_counter()
    scene = load_scene(preset)  # a bad preset is refused before the folder is claimed
    cfg = _checked_config(out_dir, frames_per_step, method, register_preset, binning, darks + flats, progress)
    out = _demo_folder(out_dir, overwrite)
    if view:
        from sim.scene import with_view

        scene = with_view(scene, view)
    if imaging:
        from sim.scene import with_imaging

        scene = with_imaging(scene, imaging)
    # binned pixels sum binning^2 pixels' charge: the same current would saturate the 12-bit ADC,
    # so the demo lowers it as the lab does and the read-out pixels keep the scene's counts
    scene = with_binning(scene, int(binning) if binning else 1)
    if coarse:  # the demo's mesh: faster to solve (benchmarks/bench_sim.py measures what it costs)
        scene.mesh.size_inclusion_mm = max(scene.mesh.size_inclusion_mm, 1.4)
        scene.mesh.size_far_mm = max(scene.mesh.size_far_mm, 8.0)
    files, timings = {}, {}
    for label, sc in (("experiment", scene), ("control", control_scene(scene))):
        path = out / f"{label}.h5"
        t = time.perf_counter()
        bench = VirtualBench(sc, progress=progress)
        p = _protocol(
            sc,
            path,
            initial_height_mm=bench.initial_height_mm,
            frames_per_step=frames_per_step,
            darks=darks,
            flats=flats,
            warm=label == "control",
            dialect=dialect,
        )
        dev = sim_devices(p, bench=bench, progress=progress)
        res = run(p, devices=dev, progress=progress)
        timings[f"acquire_{label}_s"] = time.perf_counter() - t
        if label == "experiment":  # the truth the report checks the registration against
            t = time.perf_counter()
            bench.write_truth(path)
            timings["truth_s"] = time.perf_counter() - t
        files[label] = str(path)
        if label == "experiment":
            files["frames"] = res.frames_total
            files["per_frame_overhead_ms"] = 1000 * sorted(res.per_frame_overhead_s)[len(res.per_frame_overhead_s) // 2]
    t = time.perf_counter()
    result = process(files["experiment"], cfg, out_dir=out / "results", overwrite=overwrite)
    timings["process_s"] = time.perf_counter() - t
    timings["total_s"] = time.perf_counter() - t0
    r = result.results
    return {
        "scene": scene.name,
        "dialect": dialect,
        "files": files,
        "results": r,
        "report": result.files.get("report"),
        "results_json": result.files["results_json"],
        "timings": timings,
    }


def headline(summary) -> str:
    """The table the demo prints."""
    r = summary["results"]
    ctrl = r.get("control") or {}
    main = r["main_pair"]
    lines = [
        f"scene {summary['scene']}: {summary['files']['frames']} frames acquired through the emulated L8121 "
        f"(dialect {summary.get('dialect', 'A')}) "
        f"(write + bookkeeping {summary['files']['per_frame_overhead_ms']:.1f} ms per frame)",
        "",
        f"{'':<34} {'log domain':>12} {'negative':>10}   {'control log':>12} {'control neg':>12}   paper",
    ]

    def row(label, get, paper=""):
        vals = [get(r, d) for d in ("log", "negative")]  # "negative": -I/I0, the paper's linear images
        cvals = [get(ctrl, d) if ctrl else None for d in ("log", "negative")]
        fmt = lambda v: f"{v:.3f}" if isinstance(v, (int, float)) and v == v else "-"
        lines.append(
            f"{label:<34} {fmt(vals[0]):>12} {fmt(vals[1]):>10}   {fmt(cvals[0]):>12} {fmt(cvals[1]):>12}   {paper}"
        )

    for k in ("1", "2"):
        row(
            f"improvement factor, k = {k}",
            lambda x, d, k=k: x["domains"][d]["improvement_factor"].get(k),
            {"1": "about 1.4", "2": "about 2"}[k],
        )
        row(f"  bound (rigid inclusion), k = {k}", lambda x, d, k=k: (x["domains"][d].get("bound") or {}).get(k))
    row("CNR reference", lambda x, d: x["domains"][d].get("cnr_reference"))
    for k in ("1", "2"):
        row(f"CNR enhanced, k = {k}", lambda x, d, k=k: (x["domains"][d].get("cnr") or {}).get(k))
    for pair in r["change_ratio"]:
        row(
            f"change ratio incl/bg, {pair}",
            lambda x, d, p=pair: x["change_ratio"].get(p, {}).get(d),
            "0.66-0.84" if pair == main else "",
        )
    q = r["registration"][main]
    epe = f", EPE vs truth {q['epe_median']:.2f} / {q['epe_p95']:.2f} px (median / p95)" if "epe_median" in q else ""
    lines += ["", f"registration {main} ({q['method']}): ok {q['ok']}, {q['seconds']:.1f} s, folds {q['folds']}{epe}"]
    t = summary["timings"]
    lines.append(
        f"time: acquire {t['acquire_experiment_s']:.0f} s + control {t['acquire_control_s']:.0f} s, "
        f"process {t['process_s']:.0f} s, total {t['total_s']:.0f} s"
    )
    lines.append(f"report: {summary['report']}")
    return "\n".join(lines)


def add_demo(subparsers):
    p = subparsers.add_parser(
        "demo",
        help="the whole system on the virtual bench: acquire (emulated L8121), process, report",
        description="Acquire a compression series (15, 20, 25 %) of a simulated scene through the emulated "
        "L8121 on a pseudo-terminal, then a control whose inclusion is as soft as the gel, process both "
        "and write the report; prints the headline table. About 3-6 minutes at the defaults on a shared "
        "2-core machine (187-349 s measured); --binning 2 --coarse --fast about 1.5.",
    )
    p.add_argument("-o", "--output", type=Path, default=Path("out/demo"), help="output folder (default out/demo)")
    p.add_argument("--preset", default="seed-breast", help="scene preset: seed-breast (default) or pva-phantom")
    p.add_argument(
        "--binning",
        type=int,
        choices=[1, 2, 4],
        default=1,
        help="detector binning (default 1: the full 2240 x 2240 panel; 2: 1120 x 1120, the 4 fps mode, at a "
        "quarter of the tube current)",
    )
    p.add_argument("--coarse", action="store_true", help="a coarser finite-element mesh than the scene's (faster)")
    p.add_argument("--fine", action="store_true", help=argparse.SUPPRESS)  # the default now; kept for old scripts
    p.add_argument("--fast", action="store_true", help="the fast registration presets (auto-fast), not auto")
    p.add_argument(
        "--view",
        choices=["through_plates", "side"],
        help="beam direction (default: the preset's; pva-phantom is imaged from the side)",
    )
    p.add_argument(
        "--imaging",
        choices=["paper", "experiment"],
        help="paper: monochromatic beam, no scatter; experiment: tube spectrum and scatter (default: the "
        "preset's, experiment)",
    )
    p.add_argument("--frames", type=int, default=2, help="frames per compression step (default 2)")
    p.add_argument("--method", default="rc", help="registration: rc (default), or ncc / ssd / mi (the same B-spline)")
    p.add_argument(
        "--dialect",
        choices=("A", "B"),
        default="A",
        help="the L8121 command dialect the emulated controller speaks (default A)",
    )
    p.add_argument("--overwrite", action="store_true", help="replace a previous demo's folder (never other files)")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bars")
    p.set_defaults(func=_run)


def _run(args) -> int:
    from radiokit.interrupts import exit_status

    out = Path(args.output)
    made_here = not out.exists() and not out.is_symlink()
    try:
        summary = _run_demo(args)
    except KeyboardInterrupt as exc:
        # not the other commands' "no partial output was left": the acquisitions append frame by
        # frame (not atomic), so an interrupted demo may leave its experiment files behind
        print(_interrupted_line(out, made_here), file=sys.stderr)
        return exit_status(exc)  # 130 Ctrl-C, 143 SIGTERM, 129 SIGHUP
    print()
    print(headline(summary))
    return 0


def _interrupted_line(out: Path, made_here: bool) -> str:
    """What an interrupted demo left: a folder this run made, holding nothing but its marker, is
    removed (it refused the next run, "exists; pass --overwrite", though nothing was in it)."""
    from radiokit.io import RESULTS_MARKER

    try:
        left = sorted(p.name for p in out.iterdir() if p.name != RESULTS_MARKER)
    except OSError:  # never claimed: interrupted before the folder was made
        left = []
    if not left:
        if made_here and out.is_dir():
            (out / RESULTS_MARKER).unlink(missing_ok=True)
            out.rmdir()
        return "radiokit demo: interrupted; no partial output was left"
    folder = shlex.quote(str(out))
    return (
        f"radiokit demo: interrupted; {out} keeps what it had written ({', '.join(left)}; an interrupted "
        f"acquisition keeps the frames it flushed): `radiokit demo -o {folder} --overwrite` starts again"
    )


def _run_demo(args) -> dict:
    from sim.scene import load_scene

    try:  # the option named, as `sim run --preset` names it: "unknown scene 'nope'" did not say where
        scene = load_scene(args.preset)
    except (ValueError, OSError) as exc:
        raise type(exc)(f"--preset {args.preset}: {str(exc).removeprefix(f'{args.preset}: ')}") from None
    return run_demo(
        args.output,
        preset=scene,
        binning=args.binning,
        frames_per_step=args.frames,
        coarse=args.coarse,
        method=args.method,
        register_preset="auto-fast" if args.fast else "auto",
        progress=not args.quiet and sys.stderr.isatty(),
        dialect=args.dialect,
        overwrite=args.overwrite,
        view=args.view,
        imaging=args.imaging,
    )
