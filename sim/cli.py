"""Subcommands ``sim`` contributes to the ``radiokit`` command (entry-point group radiokit.commands)."""
from __future__ import annotations

from pathlib import Path


def add_demo(subparsers):
    p = subparsers.add_parser("demo", help="run the end-to-end demo on a simulated panel and write a report")
    p.add_argument("-o", "--output", type=Path, default=Path("out/demo"), help="output folder (default out/demo)")
    p.add_argument("--binning", type=int, choices=[1, 2, 4], default=1, help="detector binning (default 1: 2240x2240)")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bars")
    p.set_defaults(func=_run_demo)


def _run_demo(args) -> int:
    from sim.demo import run_demo

    res = run_demo(args.output, binning=args.binning, progress=not args.quiet)
    d = res["defects"]
    print(f"\nexperiment file   {res['experiment']}  ({res['frame_shape'][0]}x{res['frame_shape'][1]})")
    print(f"defects           planted {d['planted']}, found {d['found']}: {d['true_positive']} right, "
          f"{d['false_positive']} false, {d['missed']} missed; defect columns {d['defect_columns']}")
    print(f"correction        {res['correct_frames_per_second']:.1f} frames/s")
    print(f"\n{'step':>4} {'ratio':>6} {'max -ln(I/I0)':>14} {'bias':>10} {'rms error':>10} {'expected noise':>15}")
    for s in res["steps"]:
        print(f"{s['step']:>4} {s['ratio']:>6.2f} {s['max_line_integral']:>14.3f} {s['bias']:>+10.5f} "
              f"{s['rms_error']:>10.5f} {s['expected_noise']:>15.5f}")
    t = res["timings"]
    print(f"\ntime: acquire {t['acquire_s']:.1f} s, calibrate {t['calibrate_s']:.1f} s, correct {t['correct_s']:.1f} s, "
          f"total {t['total_s']:.1f} s")
    print(f"figure            {res['figure']}")
    return 0
