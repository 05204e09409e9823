"""The virtual bench: the simulated experiment as the lab's devices see it.

A :class:`VirtualBench` holds one scene between two plates in front of a model C7942. The
compression frame moves the plates (:meth:`VirtualBench.set_gap`), pulls the phantom out of the
beam for flats (:attr:`VirtualBench.sample_in`), and the detector reads frames
(:meth:`VirtualBench.expose`) given the source's state. ``acquisition.frame.SimFrame`` and
``acquisition.detector.SimDetector`` are thin devices over it, so the protocol code that drives
the lab drives the simulation unchanged.

Mechanics and projection are the ones :func:`sim.lab.simulate_experiment` uses: one
:class:`sim.mechanics.Solver` per bench (the mesh is built once), states solved incrementally for
all the protocol's ratios in one :meth:`prepare`, line integrals from
:func:`sim.lab.project_state`, frames from :func:`sim.lab.make_panel`'s panel at
:func:`sim.lab.open_beam_counts`.

The bench is the panel, not a planned exposure: it never refuses a source setting. Binned, a
read-out pixel sums ``binning**2`` pixels' charge of the dose the source gives (the scene's
``i0_counts`` at its kV and µA, scaled by :meth:`VirtualBench.open_beam`), and an open beam past
the 12-bit ADC clips at 4095 as the C7942's does; the calibration then flags or refuses the
saturated flats (``radiokit.calibrate``). A protocol that bins lowers the current as the lab does.

Examples
--------
>>> from sim.scene import block_scene
>>> bench = VirtualBench(block_scene(size_mm=10, ratios=(0.2,)), binning=4)
>>> bench.initial_height_mm, bench.panel.shape
(10.0, (560, 560))
>>> bench.prepare([0.1, 0.2])
>>> bench.set_gap(8.0)
>>> round(bench.ratio, 6), round(float(bench.line_integral().max()), 6)   # 0.05 /mm x 8 mm
(0.2, 0.4)
>>> bench.expose(2, xray_on=False).shape
(2, 560, 560)
"""

from __future__ import annotations

import copy
import logging
import math
import threading
import time

import numpy as np

from sim.lab import make_panel, open_beam_counts, project_state
from sim.scene import Detector, load_scene

__all__ = ["VirtualBench"]

log = logging.getLogger(__name__)

#: a requested ratio within this of a prepared one is that one (no new solve)
SNAP = 1e-6


class VirtualBench:
    """One scene on the virtual bench: plates, phantom, panel.

    Parameters
    ----------
    scene : Scene, preset name or TOML
        Copied: the bench never changes the caller's scene.
    binning : {1, 2, 4}, optional
        Overrides ``scene.detector.binning`` (and so the projection grid) at the same source: the
        read-out pixels sum ``binning**2`` pixels' charge (:func:`sim.scene.with_binning` keeps
        their counts by lowering the current instead).
    seed : int
        The panel's fixed pattern (gain, offsets, defects), as in
        :func:`sim.lab.simulate_experiment`; also seeds the noise of :meth:`expose` calls
        without an ``rng``.
    progress : bool
        Progress bars while solving.

    Attributes
    ----------
    scene : Scene
    initial_height_mm : float
        The uncompressed height of the body along the compression axis ``y`` (twice
        ``scene.body.half_height_mm``): the plate gap at ratio 0.
    panel : sim.detector.PanelModel
    i0 : float
        Open-beam counts per unbinned pixel at the scene's exposure, whatever the binning (a
        read-out pixel collects ``i0 * binning**2``).
    sample_in : bool
        The phantom is in the beam (False: flats).

    Notes
    -----
    The compression ratio of a gap ``g`` is ``1 - g / initial_height_mm``. A gap wider than the
    body leaves it uncompressed (plates not touching): the line integral is that of ratio 0 and
    :attr:`ratio` reads negative.
    """

    def __init__(self, scene, *, binning=None, seed=0, progress=False):
        scene = copy.deepcopy(load_scene(scene))
        if binning is not None:
            # the binning alone (validated), at the same source: a dose the binned ADC cannot hold
            # clips as on the panel, it is not refused here (scene.validate() would)
            scene.detector = Detector(scene.detector.preset, int(binning))
        self.scene = scene
        self.seed = int(seed)
        self.progress = bool(progress)
        self.initial_height_mm = 2.0 * float(scene.body.half_height_mm)
        self.panel = make_panel(scene, self.seed)
        self.i0 = float(open_beam_counts(scene))
        self.sample_in = True
        self._solver = None
        self._states = {}  # ratio -> State
        self._line_integrals = {}  # ratio (0.0 for the undeformed body) -> float32 (rows, cols)
        self._masks = {}  # ratio -> uint8 (rows, cols): rays that cross an inclusion
        self._ratio = 0.0
        self._gap_mm = self.initial_height_mm
        self._rng = np.random.default_rng(self.seed)
        self._lock = threading.RLock()
        self.solve_seconds = 0.0

    # -- mechanics ------------------------------------------------------------------------------
    @property
    def solver(self):
        """The scene's :class:`sim.mechanics.Solver`, built (meshed) on first use."""
        with self._lock:
            if self._solver is None:
                from sim.mechanics import Solver

                t = time.perf_counter()
                self._solver = Solver(self.scene)
                self.solve_seconds += time.perf_counter() - t
                log.info("bench %s: meshed in %.1f s", self.scene.name, time.perf_counter() - t)
            return self._solver

    @property
    def prepared_ratios(self) -> tuple[float, ...]:
        """The ratios solved so far, ascending."""
        return tuple(sorted(self._states))

    @property
    def states(self) -> dict:
        """Solved states by ratio (a copy of the cache: ``sim.mechanics.State``)."""
        return dict(self._states)

    def _known(self, ratio):
        for r in self._states:
            if abs(r - ratio) <= SNAP:
                return r
        return None

    def prepare(self, ratios) -> None:
        """Solve every ratio in ``ratios`` not solved yet, in one incremental march.

        The solver steps the plates from 0 through the sorted ratios, each state the start of the
        next, so one call for a whole protocol costs about as much as its largest ratio alone;
        ratios within 1e-6 of a solved one, and ratio 0 (no deformation), are not solved again.
        """
        ratios = [_check_ratio(r) for r in np.atleast_1d(np.asarray(ratios, float))]
        with self._lock:
            todo = sorted({r for r in ratios if r > 0 and self._known(r) is None})
            if not todo:
                return
            solver = self.solver
            t = time.perf_counter()
            for state in solver.solve(todo, progress=self.progress):
                self._states[state.ratio] = state
            dt = time.perf_counter() - t
            self.solve_seconds += dt
            log.info("bench %s: solved ratios %s in %.1f s", self.scene.name, ", ".join(f"{r:.4g}" for r in todo), dt)

    # -- plates and phantom -----------------------------------------------------------------------
    def set_gap(self, gap_mm: float) -> None:
        """Move the plates to ``gap_mm``; a gap at or above :attr:`initial_height_mm` leaves the
        body uncompressed."""
        gap_mm = float(gap_mm)
        if not math.isfinite(gap_mm) or gap_mm <= 0:
            raise ValueError(f"bench {self.scene.name}: plate gap {gap_mm!r} mm must be a positive number")
        ratio = 1.0 - gap_mm / self.initial_height_mm
        if ratio >= 0.9:
            raise ValueError(
                f"bench {self.scene.name}: a gap of {gap_mm:.3f} mm is a compression of "
                f"{100 * ratio:.1f} % of {self.initial_height_mm:.3f} mm; the model goes to 90 %"
            )
        if 0 < ratio <= SNAP:  # the plates just touch
            ratio, gap_mm = 0.0, self.initial_height_mm
        with self._lock:
            if ratio > 0:
                known = self._known(ratio)
                if known is None:
                    self.prepare([ratio])
                    known = self._known(ratio)
                ratio = known
                gap_mm = self.initial_height_mm * (1.0 - ratio)  # the snapped state's gap
            self._ratio, self._gap_mm = ratio, gap_mm

    @property
    def ratio(self) -> float:
        """The current compression ``1 - gap / initial_height`` (negative: plates apart)."""
        return self._ratio

    @property
    def gap_mm(self) -> float:
        return self._gap_mm

    @property
    def state(self):
        """The current ``sim.mechanics.State`` (None while uncompressed)."""
        return self._states.get(self._ratio) if self._ratio > 0 else None

    # -- projection and exposure --------------------------------------------------------------
    def line_integral(self) -> np.ndarray:
        """The noise-free ``-ln(I/I0)`` of the current state on the panel grid, float32 (rows,
        cols); cached per ratio. Uncompressed: the undeformed mesh (zero displacement)."""
        return self._projection(self._ratio if self._ratio > 0 else 0.0)[0]

    def _projection(self, key):
        """(line integral, inclusion mask) of the state at ratio ``key``, projected once."""
        with self._lock:
            if key not in self._line_integrals:
                state = self._states.get(key)
                t = time.perf_counter()
                li, mask = project_state(self.scene, self.solver, None if state is None else state.displacement)
                li.setflags(write=False)
                self._line_integrals[key] = li
                self._masks[key] = mask
                log.debug("bench %s: projected ratio %.4g in %.2f s", self.scene.name, key, time.perf_counter() - t)
            return self._line_integrals[key], self._masks[key]

    def open_beam(self, kv=None, ua=None) -> float:
        """Open-beam counts per unbinned pixel at ``kv`` and ``ua`` (default: the scene's).

        The tube's output, and so the detected open-beam signal, is taken proportional to the
        current and to the square of the voltage relative to the scene's exposure,
        ``i0 * (ua / ua_scene) * (kv / kv_scene)**2``: Kramers' law, the bremsstrahlung energy ~
        I kV^2, which an energy-integrating panel's open beam follows. The L8121-01's spectrum
        through its beryllium window and 500 mm of air (SpekPy) grows a little more slowly above
        60 kV (kV^1.83-1.92: 4 % under kV^2 at 100 kV, 5 % over at 40 kV;
        ``tests/test_sim_physics_closed_form.py``, benchmarks/README.md "The tube's output against
        its voltage"). What grows faster with kV is the transmission through an object (its
        attenuation falls with energy), which this model leaves out: attenuation does not depend
        on kV here (a monoenergetic model).
        """
        ex = self.scene.exposure
        kv = ex.voltage_kv if kv is None else float(kv)
        ua = ex.current_ua if ua is None else float(ua)
        if not (math.isfinite(kv) and math.isfinite(ua)):
            raise ValueError(f"bench {self.scene.name}: beam at {kv!r} kV, {ua!r} uA is not a number")
        if kv <= 0 or ua <= 0:
            return 0.0
        return self.i0 * (ua / ex.current_ua) * (kv / ex.voltage_kv) ** 2

    def expose(self, n: int = 1, *, xray_on: bool = True, kv=None, ua=None, rng=None) -> np.ndarray:
        """Read ``n`` raw frames, (n, rows, cols) uint16.

        X-rays off (or zero kV or current): dark frames. On, phantom out: flat frames of
        :meth:`open_beam` counts. On, phantom in: exposures of :meth:`line_integral`. ``rng``
        (a ``numpy.random.Generator``) draws the noise; default the bench's own, seeded by
        ``seed``.
        """
        rng = self._rng if rng is None else rng
        i0 = self.open_beam(kv, ua) if xray_on else 0.0
        if i0 <= 0:
            return self.panel.dark_frames(n, rng)
        if not self.sample_in:
            return self.panel.flat_frames(n, i0, rng)
        return self.panel.expose(self.line_integral(), i0, n, rng)

    def write_truth(self, path, pairs=None, *, progress=False) -> dict:
        """Append ``/entry/simulation`` (as ``sim.lab.simulate_experiment`` writes it) to an
        experiment file acquired on this bench: the scene, the force-compression curve, the
        noise-free line integrals and inclusion masks of the prepared steps, and the truth
        displacement of each ``(a, b)`` step pair (1-based, ``a`` moving onto ``b``; default: the
        step before the last onto the last, the paper's pair -- each pair costs seconds at full
        resolution). Returns the timings."""
        from radiokit.io import write_simulation
        from sim.lab import body_footprint, truth_record
        from sim.truth import truth_displacement

        ratios = self.prepared_ratios
        if not ratios:
            raise ValueError("write_truth: no compressed state prepared on this bench")
        states = [self._states[r] for r in ratios]
        n = len(states)
        pairs = [(n - 1, n)] if pairs is None and n >= 2 else list(pairs or [])
        t = time.perf_counter()
        lis, masks = zip(*(self._projection(r) for r in ratios))  # the frames' own projections, cached
        t_proj = time.perf_counter() - t
        t = time.perf_counter()
        fields = {
            (a, b): truth_displacement(
                self.scene, states[b - 1], states[a - 1], body=body_footprint(self.scene, lis[b - 1])
            )
            for a, b in pairs
        }
        t_truth = time.perf_counter() - t
        gap0 = self.initial_height_mm
        write_simulation(
            path,
            truth_record(
                self.scene, states, lis, masks, fields, self.panel, dict(projection=t_proj, truth=t_truth), gap0
            ),
            replace=True,
        )
        return {"projection_s": t_proj, "truth_s": t_truth}

    def describe(self) -> dict:
        """What the bench is, JSON-able."""
        return {
            "kind": "virtual-bench",
            "scene": self.scene.name,
            "scene_toml": self.scene.to_toml(),
            "shape": list(self.panel.shape),
            "binning": self.scene.detector.binning,
            "pixel_size_mm": self.scene.detector.pixel_size_mm,
            "initial_height_mm": self.initial_height_mm,
            "i0_counts_per_unbinned_pixel": self.i0,
            "seed": self.seed,
            "prepared_ratios": list(self.prepared_ratios),
            "ratio": self.ratio,
            "gap_mm": self.gap_mm,
            "sample_in": self.sample_in,
        }

    def __repr__(self):
        return (
            f"VirtualBench({self.scene.name!r}, shape={self.panel.shape}, h0={self.initial_height_mm:g} mm, "
            f"ratio={self.ratio:.4g}, sample_in={self.sample_in})"
        )


def _check_ratio(r) -> float:
    r = float(r)
    if not (math.isfinite(r) and 0 <= r < 0.9):
        raise ValueError(f"compression ratio {r!r}: expected 0 <= ratio < 0.9")
    return r
