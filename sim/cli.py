"""Subcommands ``sim`` contributes to the ``radiokit`` command (entry-point group radiokit.commands)."""

from __future__ import annotations

import os
import sys
from pathlib import Path


def add_sim(subparsers):
    p = subparsers.add_parser("sim", help="virtual experiments: compress a scene and write simulated C7942 frames")
    sub = p.add_subparsers(dest="sim_command", metavar="{run}", required=True)
    r = sub.add_parser(
        "run",
        help="compress, project and expose a scene into an experiment file with its truth",
        description="Compress a scene (a TOML file or a preset), project each state, expose it on a "
        "model C7942 and write an experiment file with /entry/simulation (the truth).",
    )
    src = r.add_mutually_exclusive_group(required=True)
    src.add_argument("scene", nargs="?", type=Path, help="scene TOML file (`--save-scene` writes a preset's)")
    src.add_argument("--preset", help="a built-in scene: seed-breast or pva-phantom")
    r.add_argument(
        "--ratios",
        type=float,
        nargs="+",
        help="compression ratios, fractions of the body's height, increasing, each in [0, 0.9) (default: the "
        "scene's), e.g. 0.15 0.2 0.25",
    )
    r.add_argument("-o", "--output", type=Path, required=True, help="experiment file to write (.h5)")
    r.add_argument(
        "--binning",
        type=int,
        choices=[1, 2, 4],
        help="detector binning (default: the scene's); at the scene's source, so a binned pixel sums the charge "
        "of binning^2 pixels (refused where that would saturate the 12-bit ADC)",
    )
    r.add_argument("--view", choices=["through_plates", "side"], help="beam direction (default: the scene's)")
    r.add_argument(
        "--imaging",
        choices=["paper", "experiment"],
        help="paper: monochromatic, no scatter; experiment: tube spectrum and scatter (default: the scene's)",
    )
    r.add_argument("--darks", type=int, default=10, help="dark frames (default 10)")
    r.add_argument("--flats", type=int, default=10, help="flat frames (default 10)")
    r.add_argument("--frames", type=int, default=1, help="projections per compression step (default 1)")
    r.add_argument("--seed", type=int, default=0, help="noise seed (default 0)")
    r.add_argument(
        "--overwrite",
        action="store_true",
        help="replace an earlier simulation's file (never an input, nor a lab's experiment file)",
    )
    r.add_argument("--save-scene", type=Path, help="also write the scene as TOML here")
    r.add_argument("-q", "--quiet", action="store_true", help="no progress output")
    r.set_defaults(func=_run_sim)


def _run_sim(args) -> int:
    import time

    from radiokit.io import atomic_path, check_output
    from sim.lab import simulate_experiment
    from sim.scene import PRESETS, load_scene

    if args.preset is not None and args.preset not in PRESETS:
        raise ValueError(f"--preset {args.preset!r}: expected one of {', '.join(PRESETS)}")
    scene = load_scene(args.preset if args.preset is not None else str(args.scene))
    if args.binning:
        scene.detector.binning = args.binning
        try:  # the scene's source binned: each read-out pixel sums binning**2 pixels' charge
            scene.validate()
        except ValueError as exc:
            raise ValueError(f"--binning {args.binning}: {exc}") from None
    if args.ratios:  # the scene's rule: each in [0, 0.9), strictly increasing (also refuses nan)
        from sim.scene import Compression

        try:
            Compression(tuple(args.ratios), scene.compression.contact)
        except ValueError as exc:
            raise ValueError(f"--ratios {' '.join(map(str, args.ratios))}: {exc}") from None
    if args.seed < 0:  # numpy refused it only after the mechanics
        raise ValueError(f"--seed {args.seed}: expected a whole number >= 0")
    for name in ("darks", "flats", "frames"):
        # 0 darks or flats wrote a file (25 s at full size) that `process` and `correct` then
        # refused: "holds no darks (image_key 2): cannot calibrate"
        if getattr(args, name) < 1:
            why = (
                "each step needs a projection"
                if name == "frames"
                else "the experiment is corrected with its own darks and flats"
            )
            raise ValueError(f"--{name} {getattr(args, name)}: expected a count of at least 1 ({why})")
    if args.view:
        from sim.scene import with_view

        scene = with_view(scene, args.view)
    if args.imaging:
        from sim.scene import with_imaging

        scene = with_imaging(scene, args.imaging)
    scene.validate()  # the options above change it
    if args.output.suffix.lower() not in (".h5", ".hdf5", ".nxs"):
        raise ValueError(f"{args.output}: the experiment file must end in .h5")
    inputs = [args.scene] if args.scene is not None else []
    check_output(args.output, overwrite=args.overwrite, inputs=inputs)  # before minutes of mechanics
    if args.overwrite and args.output.exists():
        _refuse_replacing_raw_data(args.output)
    if args.save_scene:  # checked now, written with the experiment file: no scene of a failed run
        # the output checks first: they refuse a link in a loop in one line, where Path.resolve()
        # raises RuntimeError before Python 3.13 (a traceback); realpath leaves a loop unresolved
        check_output(args.save_scene, overwrite=args.overwrite, inputs=inputs)
        if os.path.realpath(args.save_scene) == os.path.realpath(args.output):
            raise ValueError(f"--save-scene {args.save_scene}: the same file as -o")
    rows, cols = scene.detector.shape
    n_states = len(args.ratios or scene.compression.ratios)
    # the frames (uint16), and per state a line integral and mask, per pair a truth field (float32)
    size = rows * cols * (2 * (args.darks + args.flats + args.frames * n_states) + 5 * n_states + 4 * n_states**2)
    t0 = time.perf_counter()
    say = (lambda *a, **k: None) if args.quiet else print

    def on_step(ratio, iterations, seconds):
        say(f"  load step to {100 * ratio:6.2f} %: {iterations:2d} Newton iterations, {seconds:5.1f} s", flush=True)

    def on_state(s):
        say(
            f"state {100 * s.ratio:5.1f} %: gap {s.gap_mm:7.3f} mm, plate force {s.plate_force_n:9.4f} N, "
            f"volume ratio {s.volume_ratio:.5f}, inclusion/background strain "
            f"{s.inclusion_strain / s.background_strain if s.background_strain else float('nan'):.3f}",
            flush=True,
        )

    say(
        f"scene {scene.name}: {scene.body.geometry}, {len(scene.inclusions)} inclusion(s), "
        f"detector {scene.detector.shape[0]}x{scene.detector.shape[1]} ({scene.beam.kind} beam along {scene.beam.direction})"
    )
    # written under a temporary name and renamed when complete: never a half-simulated file
    from sim.mechanics import MemoryBudgetError

    with atomic_path(args.output, overwrite=args.overwrite, inputs=inputs, size_hint=size) as tmp:
        try:
            res = simulate_experiment(
                scene,
                tmp,
                ratios=args.ratios,
                n_darks=args.darks,
                n_flats=args.flats,
                frames_per_step=args.frames,
                seed=args.seed,
                overwrite=True,
                progress=not args.quiet and sys.stderr.isatty(),
                on_state=on_state,
                on_step=on_step,
            )
        except MemoryBudgetError as exc:  # found once meshed: named with the scene it came from
            where = args.scene if args.scene is not None else f"preset {args.preset}"
            raise MemoryBudgetError(f"{where}: {exc}") from None
    if args.save_scene:
        with atomic_path(args.save_scene, overwrite=args.overwrite, inputs=inputs) as tmp:
            scene.save(tmp)
    res["file"] = str(args.output)
    sec = res["seconds"]
    print(f"\n{'step':>4} {'ratio':>6} {'gap mm':>8} {'force N':>10} {'volume':>8} {'incl/bg strain':>15}")
    for s in res["states"]:
        ratio = s["inclusion_strain"] / s["background_strain"] if s["background_strain"] else float("nan")
        print(
            f"{s['step']:>4} {s['ratio']:>6.3f} {s['gap_mm']:>8.3f} {s['plate_force_n']:>10.4f} "
            f"{s['volume_ratio']:>8.5f} {ratio:>15.3f}"
        )
    print(
        f"\nwrote {res['file']} ({res['frame_shape'][0]}x{res['frame_shape'][1]}); time: mechanics "
        f"{sec['mechanics']:.1f} s, projection {sec['projection']:.1f} s, truth {sec['truth']:.1f} s, "
        f"frames {sec['frames']:.1f} s, total {time.perf_counter() - t0:.1f} s"
    )
    return 0


def _refuse_replacing_raw_data(path: Path) -> None:
    """``--overwrite`` replaces an earlier simulation only: an experiment file without
    ``/entry/simulation`` holds frames from the lab (DESIGN.md: raw data is never modified), and a
    file that is not HDF5 at all is not radiokit's to replace either."""
    import h5py

    try:
        with h5py.File(path, "r") as f:
            simulated = "entry/simulation" in f
    except OSError:
        simulated = False
    if not simulated:
        raise ValueError(
            f"{path}: is not a simulated experiment (no /entry/simulation): --overwrite replaces only an earlier "
            "`sim run`'s file; choose another output"
        )
