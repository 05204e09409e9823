"""The virtual experiment: a scene compressed, projected and exposed into an experiment file.

The file is the one the lab writes (``radiokit.io.ExperimentWriter``: darks, flats, then the
projections of each compression step as raw uint16 C7942 frames), plus ``/entry/simulation``
holding what produced it and the truth the processing chain is checked against: a
:class:`radiokit.io.SimulationRecord` (see ``radiokit/io/_simulation.py`` for the layout),
written through :func:`radiokit.io.write_simulation`. The displacement fields are
:func:`sim.truth.truth_displacement`'s (how a 3D motion becomes a 2D pull field).

Steps are numbered from 1 in the file, in increasing compression, as the lab numbers them.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from sim.detector import PanelModel
from sim.scene import Compression, Scene, anode_for, load_scene

__all__ = ["simulate_experiment", "project_state", "body_footprint", "make_panel", "open_beam_counts", "truth_record"]


def project_state(scene: Scene, solver, displacement=None) -> tuple[np.ndarray, np.ndarray]:
    """The noise-free line integral of one state of ``solver``'s mesh, and its inclusion mask.

    Parameters
    ----------
    scene : Scene
        Beam, detector grid and attenuations (the body's, then each inclusion's).
    solver : sim.mechanics.Solver
        The mesh: its ``projection_mesh`` (the P2 nodes as a linear mesh) where it has one.
    displacement : (dim, n_dofs) array, optional
        ``State.displacement``; ``None`` projects the undeformed mesh (zero displacement).

    Returns
    -------
    line_integral : (rows, cols) float32
        ``-ln(I/I0) = sum_m mu_m L_m`` on the scene's detector grid.
    inclusion_mask : (rows, cols) uint8
        1 where the ray crosses an inclusion (all 0 for a scene without one).
    """
    from sim import imaging
    from sim.xray import Geometry, path_lengths

    mus = [scene.body.material.attenuation_per_mm] + [inc.material.attenuation_per_mm for inc in scene.inclusions]
    fem = getattr(solver, "projection_mesh", None) or solver.fem
    thickness = float(scene.body.size_mm[2]) if fem.model == "plane-strain" else None
    # (n_regions, rows, cols) mm
    geometry = Geometry.from_scene(scene)
    lengths = path_lengths(fem, geometry, displacement, thickness_mm=thickness)
    # the scene's imaging model (sim.imaging): tube spectrum and scatter, or the paper's line integral
    model = imaging.for_scene(scene, geometry.pixel_size_mm)
    line_integral = model(lengths, np.asarray(mus[: len(lengths)], np.float64)).astype(np.float32)
    mask = (lengths[1:].sum(axis=0) > 0).astype(np.uint8) if len(mus) > 1 else np.zeros(lengths.shape[1:], np.uint8)
    return line_integral, mask


def body_footprint(scene: Scene, line_integral):
    """Where the body covers the detector, from a state's projection (None, to be rendered,
    when some material does not attenuate): the ``body`` :func:`sim.truth.truth_displacement`
    takes, as :func:`simulate_experiment` and ``sim.bench`` pass it."""
    mus = [scene.body.material.attenuation_per_mm] + [inc.material.attenuation_per_mm for inc in scene.inclusions]
    return line_integral > 0 if min(mus) > 0 else None


def make_panel(scene: Scene, seed: int = 0) -> PanelModel:
    """The model C7942 of ``scene.detector`` (its binned geometry); the panel's fixed pattern
    (gain, offsets, defects) comes from ``seed + 7``."""
    det = scene.detector
    return PanelModel(rows=det.shape[0], cols=det.shape[1], binning=det.binning, seed=seed + 7)


def open_beam_counts(scene: Scene) -> float:
    """Open-beam counts per *unbinned* pixel, the ``i0`` of :class:`PanelModel`: the scene's
    ``exposure.i0_counts``, whatever the binning.

    The dose per pixel is the source's (tube current, exposure time, distance); binning sums the
    charge of ``binning**2`` pixels into one read-out, so the same source binned by 2 reads 4x the
    counts with twice the SNR (the C7942 bins by summing charge). Until session 31 this divided by
    ``binning**2`` to keep the ADC where the scene put it: a quarter of the dose per pixel and no
    SNR gain at the same recorded kV and µA. A scene whose binned open beam would clip is refused
    (:meth:`sim.scene.Scene.validate`); :func:`sim.scene.with_binning` lowers the current instead.
    """
    return scene.exposure.i0_counts


def source_record(scene: Scene) -> dict:
    """The experiment file's source: the scene's tube (the L8121-01 has a tungsten anode and runs
    40-150 kV; ``anode = "auto"`` at 35 kV or less is a molybdenum mammography tube), kV, µA."""
    ex = scene.exposure
    tube = "Hamamatsu L8121-01" if anode_for(ex.voltage_kv, scene.imaging.anode) == "W" else "Mo-anode mammography tube"
    return {"name": f"{tube} (simulated)", "voltage_kv": ex.voltage_kv, "current_ua": ex.current_ua}


def _check_counts(ratios, contact, n_darks, n_flats, frames_per_step, seed) -> None:
    """ValueError naming the argument: the ratios by the scene's own rule (:class:`Compression`:
    a repeated one was merged into one state without a word), and a negative seed failed in numpy
    only after the mechanics."""
    Compression(ratios, contact)
    for name, value, least in (
        ("n_darks", n_darks, 0),
        ("n_flats", n_flats, 0),
        ("frames_per_step", frames_per_step, 1),
    ):
        if int(value) != value or value < least:
            raise ValueError(f"{name}={value!r}: expected a whole count of at least {least}")
    if int(seed) != seed or seed < 0:
        raise ValueError(f"seed={seed!r}: expected a whole number >= 0")


def simulate_experiment(
    scene,
    output,
    *,
    ratios=None,
    n_darks=10,
    n_flats=10,
    frames_per_step=1,
    seed=0,
    overwrite=False,
    progress=True,
    on_state=None,
    on_step=None,
) -> dict:
    """Compress ``scene`` (a :class:`Scene`, preset name or TOML) to ``ratios`` (default the
    scene's), project each state, expose it on a model C7942 and write ``output``.

    ``on_state(state)`` and ``on_step(ratio, iterations, seconds)`` report progress (see
    :meth:`sim.mechanics.Solver.solve`). Returns a summary dict:
    the states' ratio, gap, plate force and volume ratio, the file, and timings.

    Examples
    --------
    >>> import tempfile, os
    >>> from sim.scene import block_scene
    >>> scene = block_scene(size_mm=10, ratios=(0.1,))
    >>> scene.detector.binning = 4
    >>> out = os.path.join(tempfile.mkdtemp(), "sim.h5")
    >>> res = simulate_experiment(scene, out, n_darks=2, n_flats=2, progress=False)
    >>> res["states"][0]["ratio"], round(res["states"][0]["gap_mm"], 3)
    (0.1, 9.0)
    """
    from radiokit.io import ExperimentWriter, ImageKey
    from radiokit.progress import tqdm
    from sim.mechanics import compress
    from sim.truth import truth_displacement

    scene = load_scene(scene).validate()
    output = Path(output)
    if output.exists() and not overwrite:
        raise FileExistsError(f"{output}: exists (pass overwrite=True, or --overwrite on the command line)")
    ratios = tuple(sorted(float(r) for r in (scene.compression.ratios if ratios is None else ratios)))
    _check_counts(ratios, scene.compression.contact, n_darks, n_flats, frames_per_step, seed)  # before the mechanics
    t0 = time.perf_counter()
    states = compress(scene, ratios, progress=progress and on_step is None, on_state=on_state, on_step=on_step)
    t_mech = time.perf_counter() - t0

    t = time.perf_counter()
    line_integrals, masks = [], []
    for s in tqdm(states, desc="project", unit="state", disable=not progress):
        line_integral, mask = project_state(scene, states[0].solver, s.displacement)
        line_integrals.append(line_integral)
        masks.append(mask)
    t_proj = time.perf_counter() - t

    t = time.perf_counter()
    fields = {}
    for b in range(len(states)):
        for a in range(b):
            fields[(a + 1, b + 1)] = truth_displacement(
                scene, states[b], states[a], body=body_footprint(scene, line_integrals[b])
            )
    t_truth = time.perf_counter() - t

    t = time.perf_counter()
    det = scene.detector
    panel = make_panel(scene, seed)
    i0 = open_beam_counts(scene)
    rng = np.random.default_rng(seed)
    ex = scene.exposure
    src = source_record(scene)
    gap0 = states[0].gap_mm / (1 - states[0].ratio) if states[0].ratio < 1 else float("nan")
    n_frames = n_darks + n_flats + frames_per_step * len(states)
    with (
        ExperimentWriter(
            output,
            shape=panel.shape,
            overwrite=overwrite,
            pixel_size_mm=det.pixel_size_mm,
            pixel_size_from=det.pixel_size_from,
            detector_name=det.panel_name,
            bit_depth=panel.bits,  # readers then know the ADC's top without inferring it
            source=src,
            title=f"radiokit simulation: {scene.name}",
        ) as w,
        tqdm(total=n_frames, desc="expose", unit="frame", disable=not progress) as bar,
    ):
        w.set_pixel_mask(np.zeros(panel.shape, np.uint32))
        for frame in panel.dark_frames(n_darks, rng):
            w.append(frame, image_key=ImageKey.DARK)
            bar.update()
        for frame in panel.flat_frames(n_flats, i0, rng):
            w.append(frame, image_key=ImageKey.FLAT, voltage_kv=ex.voltage_kv, current_ua=ex.current_ua)
            bar.update()
        for step, (s, li) in enumerate(zip(states, line_integrals), start=1):
            for frame in panel.expose(li, i0, frames_per_step, rng):
                w.append(
                    frame,
                    image_key=ImageKey.PROJECTION,
                    step=step,
                    ratio=s.ratio,
                    gap_mm=s.gap_mm,
                    voltage_kv=ex.voltage_kv,
                    current_ua=ex.current_ua,
                )
                bar.update()
        t_frames = time.perf_counter() - t
        w.write_simulation(
            truth_record(
                scene,
                states,
                line_integrals,
                masks,
                fields,
                panel,
                dict(mechanics=t_mech, projection=t_proj, truth=t_truth, frames=t_frames),
                gap0,
            )
        )
    return {
        "file": str(output),
        "scene": scene.name,
        "frame_shape": list(panel.shape),
        "states": [
            {
                "step": i + 1,
                "ratio": s.ratio,
                "gap_mm": s.gap_mm,
                "plate_force_n": s.plate_force_n,
                "volume_ratio": s.volume_ratio,
                "inclusion_strain": s.inclusion_strain,
                "background_strain": s.background_strain,
                "newton_iterations": s.newton_iterations,
            }
            for i, s in enumerate(states)
        ],
        "seconds": {
            "mechanics": t_mech,
            "projection": t_proj,
            "truth": t_truth,
            "frames": t_frames,
            "total": time.perf_counter() - t0,
        },
    }


def truth_record(scene: Scene, states, line_integrals, masks, fields, panel, seconds, gap0):
    """The :class:`radiokit.io.SimulationRecord` of simulated ``states``: the scene, the
    force-compression curve, the noise-free projections, the truth fields ``{(a, b): field}``
    (1-based steps) and ``panel``'s planted defects."""
    from radiokit.io import PlantedDefects, SimulationRecord

    t = panel.truth
    curve = {
        name: np.array([getattr(s, name) for s in states], np.float64)
        for name in ("ratio", "gap_mm", "plate_force_n", "volume_ratio", "inclusion_strain", "background_strain")
    }
    return SimulationRecord(
        scene_toml=scene.to_toml(),
        line_integral=np.stack(line_integrals),
        inclusion_mask=np.stack(masks),
        steps=tuple(range(1, len(states) + 1)),
        displacement=dict(fields),
        defects=PlantedDefects(t.dead, t.under, t.noisy, t.columns),
        initial_gap_mm=gap0,
        seconds=dict(seconds),
        **curve,
    )
