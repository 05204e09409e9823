"""What each modelling choice changes in the paper's headline numbers, and what it costs.

Run (from the repository root)::

    python benchmarks/bench_model.py                 # about 10-15 minutes on two shared cores
    python benchmarks/bench_model.py --quick         # pva-phantom only, no 3-D default mesh: ~3 minutes
    python benchmarks/bench_model.py --full          # adds the refined meshes (seed-breast 0.7/4.2 mm): much longer
    python benchmarks/bench_model.py --out DIR       # where the JSON goes (default out/bench_model)
    python benchmarks/bench_model.py --imaging-only  # the base and the imaging rows only (~2 minutes)
    python benchmarks/bench_model.py --convergence   # the 3-D seed-breast mesh study instead (long)
    python benchmarks/bench_model.py --convergence --meshes 1.4/12/2 0.7/6/1   # the preset and its double

Needs the ``study`` extra (SpekPy, XrayDB) for the polychromatic beam.

For ``seed-breast`` (through the plates) and ``pva-phantom`` (both views: the preset's side view
and through the plates), one modelling choice at a time is switched against a base model, and
the headline numbers of the paper's pair (step 2, 20 %, registered onto step 3, 25 %) are
measured with ``sim.study`` the same way every time: the truth field registers the pair (the
registration's own error is ``bench_register.py``'s subject and the registration chart's), ROIs
from the inclusion's shadow (``radiokit.measure.find_rois``), 0.3 mm pixels, noise-free except
in the noise row.

The base model is the cheapest: the demo's coarse mesh (1.4 mm at the inclusion, 8 mm far), the
preset's materials (seed-breast: sliding chest wall, St Venant-Kirchhoff inclusion; pva-phantom:
neo-Hookean inclusion, 3-D), FEBio's coupled neo-Hookean energy, a monochromatic beam, no
scatter, an ideal detector. The choices:

- **mesh**: the scene's default mesh (1.0 / 6.0 or 5.0 mm); ``--full`` also 0.7 / 4.2 mm;
- **model**: the axisymmetric reduction (pva-phantom only: its box inclusion becomes the cylinder
  of equal section; seed-breast's half-ellipsoid with a chest wall has none);
- **wall**: the chest wall fixed (the paper's) instead of sliding (seed-breast only);
- **inclusion**: neo-Hookean instead of St Venant-Kirchhoff (seed-breast), or the reverse;
- **energy**: ANSYS's uncoupled neo-Hookean (the paper's package) instead of FEBio's coupled one,
  for every neo-Hookean material;
- **beam**: polychromatic (``sim.imaging.Polychromatic``: SpekPy spectrum, XrayDB attenuation;
  seed-breast 28 kV molybdenum with 30 um Mo, the scene's mammography label; pva-phantom the
  L8121-01's 60 kV tungsten with 150 um Be; both through 500 mm of air), matched to the scene's
  coefficients at the body's thickness along the beam (``sim.imaging.match_thickness_mm``);
- **scatter**: a smooth additive term (``sim.imaging.scatter``), scatter-to-primary 0.3 (a 5-6 cm
  object without a grid) through that thickness, Gaussian of 10 mm;
- **blur**: the scintillator's point spread (GOS on a fibre-optic plate, ../shared/hardware/C7942.md), Gaussian sigma 0.1 mm;
- **the presets' imaging** (``sim.scene.Imaging`` "experiment": polychromatic + scatter) and the
  richest imaging (+ blur): the defaults rule's check;
- **noise**: Poisson at the scene's exposure (2500 quanta per 50 um pixel, i.e. 90 000 per 0.3 mm
  pixel), mean and standard deviation over 5 seeds.

Quantities: the change ratio (negative domain, the paper's ``-I/I0``), IF(1) and IF(2) (negative), IF(1)
in the log domain, the bound (through the plates), and CNR at k = 1 (negative): for noise-free rows
*predicted* from the Poisson model at the scene's exposure (``sim.study.predicted_cnr``), for the
noise row measured. ``d%`` is the largest relative change of CR, IF(1), IF(2) and CNR against the
base; a choice "matters" when it exceeds 1 %. Seconds: the mechanics for rows that solve again,
the imaging otherwise (the base's mechanics is printed on its own row).

The machine is shared (the load average is printed); times vary by tens of percent, the numbers
are deterministic.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from sim import imaging, study
from sim.mechanics import compress
from sim.scene import load_scene, with_view

PIXEL_MM = 0.3
RATIOS = (0.20, 0.25)
COARSE = (1.4, 8.0)


@dataclasses.dataclass
class Row:
    scene: str
    choice: str
    cr: float
    if1: float
    if2: float
    if1_log: float
    bound1: float | None
    cnr1: float
    cnr_ref: float
    seconds: float
    spread: dict = dataclasses.field(default_factory=dict)


def _counts(scene):
    return scene.exposure.i0_counts * (PIXEL_MM / 0.05) ** 2


def _row(scene, name, choice, pair, seconds, counts):
    h = study.headline(pair)
    c = study.predicted_cnr(pair, h, counts, "negative")
    return Row(
        name,
        choice,
        h.change_ratio["negative"],
        h.improvement["negative"]["1"],
        h.improvement["negative"]["2"],
        h.improvement["log"]["1"],
        h.bound["negative"]["1"],
        c["1"],
        c["reference"],
        seconds,
    )


def _variants(name, quick, full):
    """(label, scene mutator) of the mechanical choices for a preset."""
    out = []
    m = load_scene(name).mesh
    default = (m.size_inclusion_mm, m.size_far_mm, m.size_contact_mm)
    if not quick:
        label = "/".join(f"{x:g}" for x in default if x is not None)
        out.append((f"mesh {label} mm (the preset's)", lambda s: _mesh(s, *default)))
    if full:
        out.append(("mesh 0.7/4.2 mm", lambda s: _mesh(s, 0.7, 4.2)))
    if name == "pva-phantom":
        out.append(("axisymmetric model", lambda s: setattr(s.mesh, "model", "axisymmetric")))
        out.append(("inclusion St Venant-Kirchhoff", lambda s: _inclusion_model(s, "linear")))
    else:
        out.append(("chest wall fixed", lambda s: setattr(s, "wall", "fixed")))
        out.append(("inclusion neo-Hookean", lambda s: _inclusion_model(s, "neo-hookean")))
    out.append(("uncoupled energy (ANSYS)", _uncoupled))
    return out


def _mesh(s, a, b, c=None):
    s.mesh.size_inclusion_mm, s.mesh.size_far_mm, s.mesh.size_contact_mm = a, b, c


def _inclusion_model(s, model):
    s.inclusions = [dataclasses.replace(i, material=dataclasses.replace(i.material, model=model)) for i in s.inclusions]


def _uncoupled(s):
    if s.body.material.model == "neo-hookean":
        s.body = dataclasses.replace(
            s.body, material=dataclasses.replace(s.body.material, model="neo-hookean-uncoupled")
        )
    s.inclusions = [
        dataclasses.replace(i, material=dataclasses.replace(i.material, model="neo-hookean-uncoupled"))
        if i.material.model == "neo-hookean"
        else i
        for i in s.inclusions
    ]


def _base(name):
    s = load_scene(name)
    s.mesh.model = "3d"
    _mesh(s, *COARSE)
    s.mesh.size_contact_mm = None
    return s


def _beam(name, base):
    """The scene's tube (sim.imaging.tube: 28 kV Mo/Mo for seed-breast, 60 kV W/Be for the pva-phantom)."""
    return imaging.tube(base.exposure.voltage_kv, "auto", imaging.match_thickness_mm(base))


def _image_rows(scene, label, proj, counts, t_proj, beam):
    rows = []
    l_ref = scene.body.material.attenuation_per_mm * imaging.match_thickness_mm(scene)
    mono = imaging.monochromatic
    sc = lambda L: imaging.scatter(L, 0.3, 10.0, PIXEL_MM, l_ref)
    bl = lambda L: imaging.blur(L, 0.1, PIXEL_MM)
    cases = [
        ("polychromatic beam", imaging.chain(beam)),
        ("scatter SPR 0.3", imaging.chain(mono, sc)),
        ("blur 0.1 mm", imaging.chain(mono, bl)),
        # the presets' imaging (sim.scene.Imaging "experiment"), and the richest imaging
        ("polychromatic + scatter (the presets')", imaging.chain(beam, sc)),
        ("polychromatic + scatter + blur", imaging.chain(beam, sc, bl)),
    ]
    for choice, model in cases:
        t = time.perf_counter()
        pair = study.images(proj, model)
        rows.append(_row(scene, label, choice, pair, t_proj + time.perf_counter() - t, counts))
    t = time.perf_counter()
    samples = []
    for seed in range(5):
        rng = np.random.default_rng(seed)
        pair = study.images(proj, imaging.chain(mono, lambda L, rng=rng: study.add_noise(L, counts, rng)))
        h = study.headline(pair)
        samples.append(
            (
                h.change_ratio["negative"],
                h.improvement["negative"]["1"],
                h.improvement["negative"]["2"],
                h.improvement["log"]["1"],
                h.cnr["negative"]["1"],
                h.cnr_reference["negative"],
            )
        )
    a = np.array(samples)
    m, sd = a.mean(axis=0), a.std(axis=0, ddof=1)
    r = Row(
        label,
        "noise (5 seeds)",
        m[0],
        m[1],
        m[2],
        m[3],
        rows[0].bound1,
        m[4],
        m[5],
        (t_proj + time.perf_counter() - t) / 5,
        spread={"cr": sd[0], "if1": sd[1], "if2": sd[2], "if1_log": sd[3], "cnr1": sd[4]},
    )
    rows.append(r)
    return rows


def run_scene(name, view, quick, full, log, imaging_only=False):
    label = name if view is None else f"{name} ({view.replace('_', ' ')})"
    base = _base(name)
    if view:
        base = with_view(base, view)
    counts = _counts(base)
    rows = []
    t = time.perf_counter()
    states = compress(base, RATIOS)
    t_mech = time.perf_counter() - t
    t = time.perf_counter()
    proj = study.project_pair(base, states, pixel_size_mm=PIXEL_MM)
    t_proj = time.perf_counter() - t
    rows.append(
        _row(base, label, f"base (coarse {COARSE[0]}/{COARSE[1]} mm, mechanics)", study.images(proj), t_mech, counts)
    )
    log(rows[-1])
    for r in _image_rows(base, label, proj, counts, t_proj, _beam(name, base)):
        rows.append(r)
        log(r)
    for choice, mutate in [] if imaging_only else _variants(name, quick, full):
        sc = dataclasses.replace(base)
        sc.mesh = dataclasses.replace(base.mesh)
        mutate(sc)
        t = time.perf_counter()
        st = compress(sc, RATIOS)
        secs = time.perf_counter() - t
        rows.append(_row(sc, label, choice, study.image_pair(sc, st, pixel_size_mm=PIXEL_MM), secs, counts))
        log(rows[-1])
    return rows


def _fmt(x, spec=".3f"):
    return "-" if x is None or (isinstance(x, float) and not math.isfinite(x)) else format(x, spec)


def _delta(r, base):
    ch = [
        abs(getattr(r, k) / getattr(base, k) - 1)
        for k in ("cr", "if1", "if2", "cnr1")
        if getattr(base, k) and math.isfinite(getattr(r, k))
    ]
    return 100 * max(ch) if ch else float("nan")


def table(rows) -> str:
    head = (
        "| scene | choice | change ratio | IF(1) | IF(2) | IF(1) log | bound k=1 | CNR k=1 (ref) | d% | matters | s |\n"
        "|---|---|---|---|---|---|---|---|---|---|---|"
    )
    out = [head]
    base = None
    for r in rows:
        if r.choice.startswith("base"):
            base = r
        d = _delta(r, base) if r is not base else 0.0
        sd = r.spread
        pm = (lambda k, v: f"{_fmt(v)} ± {_fmt(sd[k])}") if sd else (lambda k, v: _fmt(v))  # noqa: B023 (called in this iteration)
        out.append(
            f"| {r.scene} | {r.choice} | {pm('cr', r.cr)} | {pm('if1', r.if1)} | {pm('if2', r.if2)} | "
            f"{pm('if1_log', r.if1_log)} | {_fmt(r.bound1)} | {_fmt(r.cnr1, '.2f')} ({_fmt(r.cnr_ref, '.2f')}) | "
            f"{_fmt(d, '.1f')} | {'' if r is base else ('yes' if d > 1 else 'no')} | {_fmt(r.seconds, '.1f')} |"
        )
    return "\n".join(out)


#: (at the inclusion, far, at the plates or None) in mm: the README's convergence table. Each
#: banded mesh is followed by its double (every size halved), the preset's (sim.scene) first.
CONVERGENCE = [
    (2.8, 16.0, None),
    (2.0, 12.0, None),
    (1.4, 8.0, None),
    (1.0, 6.0, None),
    (0.7, 6.0, None),
    (2.0, 12.0, 2.0),
    (1.0, 6.0, 1.0),
    (1.4, 12.0, 2.0),
    (0.7, 6.0, 1.0),
]


def _parse_mesh(text):
    """``"1.4/12/2"`` -> (1.4, 12.0, 2.0); a missing third size is no contact band."""
    parts = [float(x) for x in text.split("/")]
    return tuple(parts) if len(parts) == 3 else (parts[0], parts[1], None)


def convergence_row(a, b, c) -> dict:
    """seed-breast (3-D, through the plates, its own three states) at one mesh: unknowns, seconds
    and the solver's work, the 25 % state's force and inclusion strain, and the 20 -> 25 % pair's
    change ratio and IF (negative), truth-registered."""
    sc = load_scene("seed-breast")
    sc.mesh.size_inclusion_mm, sc.mesh.size_far_mm, sc.mesh.size_contact_mm = a, b, c
    t = time.perf_counter()
    st = compress(sc)
    secs = time.perf_counter() - t
    pair = [s for s in st if s.ratio in RATIOS]
    h = study.headline(study.image_pair(sc, pair, pixel_size_mm=PIXEL_MM))
    s, sv = st[-1], st[-1].solver
    return dict(
        mesh=[a, b, c],
        dofs=int(sv.ndof),
        seconds=secs,
        newton=sum(x.newton_iterations for x in st),
        load_steps=s.load_steps,
        factorisations=sv.factorisations,
        gmres=sv.krylov_iterations,
        force=s.plate_force_n,
        strain=s.inclusion_strain,
        cr=h.change_ratio["negative"],
        if1=h.improvement["negative"]["1"],
        if2=h.improvement["negative"]["2"],
        load=os.getloadavg()[0],
    )


def convergence_table(rows) -> str:
    """The rows as markdown; a mesh whose double is also in ``rows`` gets the largest relative
    change of force, inclusion strain, change ratio, IF(1) and IF(2) on doubling."""
    lines = [
        "| mesh at inclusion / far / plates (mm) | unknowns | s (3 states) | Newton / factorisations / GMRES | "
        "force (N) | inclusion strain | change ratio (lin) | IF(1) | IF(2) | doubling changes |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    keys = ("force", "strain", "cr", "if1", "if2")
    by_mesh = {tuple(r["mesh"]): r for r in rows}
    for r in rows:
        a, b, c = r["mesh"]
        fine = by_mesh.get((a / 2, b / 2, c / 2 if c else None))
        d = f"{100 * max(abs(r[k] / fine[k] - 1) for k in keys):.1f} %" if fine else ""
        mesh = f"{a:g} / {b:g}" + (f" / {c:g}" if c else "")
        lines.append(
            f"| {mesh} | {r['dofs']} | {r['seconds']:.0f} | {r['newton']} / {r['factorisations']} / "
            f"{r['gmres']} | {r['force']:.4f} | {r['strain']:.4f} | {r['cr']:.3f} | {r['if1']:.3f} | "
            f"{r['if2']:.3f} | {d} |"
        )
    return "\n".join(lines)


def convergence(out, meshes=None) -> str:
    """Every mesh of ``meshes`` (default :data:`CONVERGENCE`), one JSON line each in
    ``out/convergence.jsonl`` as it finishes, then the table (``out/convergence.md``)."""
    rows = []
    with open(out / "convergence.jsonl", "a") as log:
        for mesh in meshes or CONVERGENCE:
            rows.append(convergence_row(*mesh))
            log.write(json.dumps(rows[-1]) + "\n")
            log.flush()
            print(rows[-1], flush=True)
    text = convergence_table(rows)
    print(text)
    (out / "convergence.md").write_text(text + "\n")
    return text


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    mode = ap.add_mutually_exclusive_group()
    mode.add_argument("--quick", action="store_true", help="pva-phantom only, no default-mesh rows")
    mode.add_argument("--full", action="store_true", help="add the refined meshes")
    mode.add_argument("--convergence", action="store_true", help="the 3-D seed-breast mesh study instead")
    mode.add_argument("--imaging-only", action="store_true", help="the base and the imaging rows only (minutes)")
    ap.add_argument(
        "--meshes",
        nargs="+",
        type=_parse_mesh,
        help="with --convergence: these meshes only (inclusion/far[/plates] mm, e.g. 2/12/2)",
    )
    ap.add_argument("--out", type=Path, default=Path("out/bench_model"))
    args = ap.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    print(f"load average before: {os.getloadavg()}", flush=True)
    if args.convergence:
        convergence(args.out, args.meshes)
        print(f"load average after: {os.getloadavg()}")
        return 0

    def log(r):
        print(
            f"  {r.scene:<34} {r.choice:<40} CR {r.cr:.4f} IF1 {r.if1:.4f} IF2 {r.if2:.4f} "
            f"IFlog {r.if1_log:.4f} CNR1 {r.cnr1:.3g} ({r.seconds:.1f} s)",
            flush=True,
        )

    rows = []
    cases = [("pva-phantom", None), ("pva-phantom", "through_plates")]
    if not args.quick:
        cases.insert(0, ("seed-breast", None))
    t0 = time.perf_counter()
    for name, view in cases:
        rows += run_scene(name, view, args.quick, args.full, log, args.imaging_only)
    text = table(rows)
    print()
    print(text)
    print(f"\ntotal {time.perf_counter() - t0:.0f} s; load average after: {os.getloadavg()}")
    (args.out / "bench_model.json").write_text(json.dumps([dataclasses.asdict(r) for r in rows], indent=1))
    (args.out / "bench_model.md").write_text(text + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
