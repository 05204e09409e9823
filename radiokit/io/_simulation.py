"""The simulation truth: what produced a simulated experiment file, and what processing must find.

Only simulated experiment files have it; ``sim.lab`` and ``sim.bench`` write it through
:func:`write_simulation`, the pipeline reads it through :func:`read_simulation`.

``/entry/simulation`` (NXcollection)
    ``@scene`` (TOML text), ``@initial_gap_mm``, ``@seconds_*`` timings;
    ``ratio``, ``gap_mm``, ``plate_force_n``, ``volume_ratio``, ``inclusion_strain``,
    ``background_strain`` (n_steps,): the force-compression curve;
    ``line_integral`` (n_steps, rows, cols) float32: noise-free ``-ln(I/I0)``;
    ``inclusion_mask`` (n_steps, rows, cols) uint8: rays that cross an inclusion;
    ``displacement/step{a}_to_step{b}`` (2, rows, cols) float32: the pull field, in pixels,
    (row, col) order, that registers step ``a`` (moving) onto step ``b`` (fixed), ``a < b``;
    ``defects/{dead,under,noisy}`` (k, 2) and ``defects/columns`` (m,): the panel's planted defects.

Steps are numbered from 1, in increasing compression, as the lab numbers them.
"""

from __future__ import annotations

import math
import re
import tomllib
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

import h5py
import numpy as np

from radiokit.checks import toml_loads
from radiokit.errors import FormatError
from radiokit.io._experiment import check_links, checked_dataset
from radiokit.io._layout import ReadBudget, check_finite, open_layout, text

__all__ = [
    "SIMULATION",
    "SimulationRecord",
    "PlantedDefects",
    "write_simulation",
    "read_simulation",
    "displacement_name",
]

#: the group, inside an experiment file
SIMULATION = "entry/simulation"
#: the force-compression curve, one value per step
CURVE = ("ratio", "gap_mm", "plate_force_n", "volume_ratio", "inclusion_strain", "background_strain")
LINE_INTEGRAL = "line_integral"
INCLUSION_MASK = "inclusion_mask"
DISPLACEMENT = "displacement"
DEFECTS = "defects"
DEFECT_KINDS = ("dead", "under", "noisy")
CONVENTION = (
    "pull, pixels, (row, col): moving(x + d(x)) matches fixed(x); "
    "attenuation-weighted mean along each ray of the fixed state; 0 off the body"
)
_PAIR = re.compile(r"step(\d+)_to_step(\d+)$")


def displacement_name(moving_step: int, fixed_step: int) -> str:
    """The dataset (inside ``displacement/``) of the truth field from ``moving_step`` onto ``fixed_step``."""
    return f"step{int(moving_step)}_to_step{int(fixed_step)}"


@dataclass(frozen=True)
class PlantedDefects:
    """The defects the model panel was given: ``(k, 2)`` (row, col) pixels and whole columns."""

    dead: np.ndarray
    under: np.ndarray
    noisy: np.ndarray
    columns: np.ndarray


@dataclass(frozen=True)
class SimulationRecord:
    """The truth of one simulated experiment.

    Attributes
    ----------
    scene_toml : str
        The scene that produced the file (``sim.scene.Scene.to_toml``).
    ratio, gap_mm, plate_force_n, volume_ratio, inclusion_strain, background_strain : (n_steps,) array
        The force-compression curve.
    line_integral : (n, rows, cols) float32
        Noise-free ``-ln(I/I0)`` of the steps in ``steps``.
    inclusion_mask : (n, rows, cols) uint8
        1 where a ray crosses an inclusion, for the steps in ``steps``.
    steps : tuple of int
        The 1-based steps ``line_integral`` and ``inclusion_mask`` hold (all, unless the reader
        was asked for fewer).
    displacement : mapping (moving_step, fixed_step) -> (2, rows, cols) float32
        The truth pull fields, in pixels, (row, col).
    defects : PlantedDefects or None
    initial_gap_mm : float
        The plate gap before compression.
    seconds : mapping str -> float
        How long each stage of the simulation took.
    """

    scene_toml: str
    ratio: np.ndarray
    gap_mm: np.ndarray
    plate_force_n: np.ndarray
    volume_ratio: np.ndarray
    inclusion_strain: np.ndarray
    background_strain: np.ndarray
    line_integral: np.ndarray
    inclusion_mask: np.ndarray
    steps: tuple = ()
    displacement: Mapping = field(default_factory=dict)
    defects: PlantedDefects | None = None
    initial_gap_mm: float = math.nan
    seconds: Mapping = field(default_factory=dict)

    @property
    def scene_name(self) -> str | None:
        """The scene's ``name``, from its TOML."""
        try:
            name = toml_loads(self.scene_toml).get("name")
        except tomllib.TOMLDecodeError:
            return None
        return name if isinstance(name, str) else None

    def step_index(self, step: int) -> int:
        """Where 1-based ``step`` lies in ``line_integral`` and ``inclusion_mask``."""
        steps = self.steps or tuple(range(1, len(self.line_integral) + 1))
        return steps.index(int(step))


def write_simulation(target, record: SimulationRecord, *, replace: bool = False) -> None:
    """Write ``record`` as ``/entry/simulation`` of an experiment file.

    Parameters
    ----------
    target : h5py.File, ExperimentWriter, str or Path
        The open experiment file, its writer, or the path of a closed one (opened to append).
    record : SimulationRecord
    replace : bool
        Replace an ``/entry/simulation`` already there; otherwise one there is an error.
    """
    if isinstance(target, (str, Path)):
        with h5py.File(target, "r+") as h5:
            write_simulation(h5, record, replace=replace)
        return
    h5 = getattr(target, "h5", target)
    if SIMULATION in h5:
        if not replace:
            raise FileExistsError(f"{h5.filename}: already holds /{SIMULATION}")
        del h5[SIMULATION]
    g = h5.create_group(SIMULATION)
    g.attrs["NX_class"] = "NXcollection"
    g.attrs["scene"] = record.scene_toml
    g.attrs["initial_gap_mm"] = float(record.initial_gap_mm)
    for k, v in record.seconds.items():
        g.attrs[f"seconds_{k}"] = float(v)
    for name in CURVE:
        g[name] = np.asarray(getattr(record, name), np.float64)
    g["plate_force_n"].attrs["units"] = "N"
    g["gap_mm"].attrs["units"] = "mm"
    opts = dict(chunks=(1,) + record.line_integral.shape[1:], compression="lzf")
    g.create_dataset(LINE_INTEGRAL, data=np.asarray(record.line_integral, np.float32), **opts)
    g[LINE_INTEGRAL].attrs["definition"] = "-ln(I/I0), noise-free, on the detector grid"
    g.create_dataset(INCLUSION_MASK, data=np.asarray(record.inclusion_mask, np.uint8), **opts)
    d = g.create_group(DISPLACEMENT)
    d.attrs["convention"] = CONVENTION
    for (a, b), values in record.displacement.items():
        ds = d.create_dataset(
            displacement_name(a, b),
            data=np.asarray(values, np.float32),
            chunks=(1,) + np.shape(values)[1:],
            compression="lzf",
        )
        ds.attrs["moving_step"], ds.attrs["fixed_step"] = int(a), int(b)
    if record.defects is not None:
        dg = g.create_group(DEFECTS)
        for name in DEFECT_KINDS:
            dg[name] = np.asarray(getattr(record.defects, name), np.int64).reshape(-1, 2)
        dg["columns"] = np.asarray(record.defects.columns, np.int64)
    h5.flush()


def read_simulation(path, *, steps=None, pairs=None, allow_external=False) -> SimulationRecord | None:
    """The simulation truth of an experiment file, or ``None`` for a file the lab acquired.

    Parameters
    ----------
    path : str or Path
    steps : iterable of int, optional
        The 1-based steps whose line integral and inclusion mask to load (default all; negative
        numbers count from the last, as in Python).
    pairs : iterable of (moving_step, fixed_step), optional
        The truth fields to load (default all the file holds); pairs the file lacks are left out.

    Raises
    ------
    FormatError
        ``/entry/simulation`` is there but not of this layout.

    Examples
    --------
    >>> import numpy as np, tempfile, os
    >>> from radiokit.io import ExperimentWriter, SimulationRecord, read_simulation
    >>> path = os.path.join(tempfile.mkdtemp(), "sim.h5")
    >>> curve = np.array([0.1, 0.2])
    >>> record = SimulationRecord('name = "block"', curve, curve, curve, curve, curve, curve,
    ...                           np.zeros((2, 4, 5), np.float32), np.zeros((2, 4, 5), np.uint8),
    ...                           displacement={(1, 2): np.zeros((2, 4, 5), np.float32)})
    >>> with ExperimentWriter(path, shape=(4, 5)) as w:
    ...     w.write_simulation(record)
    >>> sim = read_simulation(path, steps=[-1])
    >>> sim.scene_name, sim.steps, sorted(sim.displacement)
    ('block', (2,), [(1, 2)])
    """
    with open_layout(path, "an experiment file") as h5:
        check_links(path, h5, SIMULATION, allow_external)
        if SIMULATION not in h5:
            return None
        g = h5[SIMULATION]
        if not isinstance(g, h5py.Group):
            raise FormatError(path, f"/{SIMULATION} is not a group")

        def numbers(name, ndims):
            return checked_dataset(path, h5, f"{SIMULATION}/{name}", "iuf", ndims, allow_external)

        budget = ReadBudget(path)
        curve = _read_curve(path, numbers, budget)
        n_steps = len(curve["ratio"])
        chosen = (
            tuple(range(1, n_steps + 1))
            if steps is None
            else tuple(int(s) if s > 0 else n_steps + 1 + int(s) for s in steps)
        )
        if any(not 1 <= s <= n_steps for s in chosen):
            raise FormatError(path, f"steps {list(steps)}: /{SIMULATION} holds steps 1..{n_steps}")
        images = _read_images(path, numbers, n_steps, chosen, budget)
        frame = images[LINE_INTEGRAL].shape[1:]
        fields, group = {}, g.get(DISPLACEMENT, {})
        if not isinstance(group, (h5py.Group, dict)):
            raise FormatError(path, f"/{SIMULATION}/{DISPLACEMENT} is not a group")
        for name in group:
            match = _PAIR.match(name)
            pair = (int(match[1]), int(match[2])) if match else None
            if pair and (pairs is None or pair in set(map(tuple, pairs))):
                ds = numbers(f"{DISPLACEMENT}/{name}", (3,))
                if ds.shape != (2,) + frame or not 1 <= pair[0] <= n_steps or not 1 <= pair[1] <= n_steps:
                    raise FormatError(
                        path,
                        f"/{ds.name.lstrip('/')} is {ds.shape}: expected {(2, *frame)}, between steps 1..{n_steps}",
                    )
                fields[pair] = budget.read(ds)
        defects = None
        if DEFECTS in g:
            defects = PlantedDefects(
                *(budget.read(numbers(f"{DEFECTS}/{k}", (2,))) for k in DEFECT_KINDS),
                budget.read(numbers(f"{DEFECTS}/columns", (1,))),
            )
            if any(d.shape[1] != 2 for d in (defects.dead, defects.under, defects.noisy)):
                raise FormatError(path, f"/{SIMULATION}/{DEFECTS}/dead, under and noisy must be (k, 2) pixels")
        return SimulationRecord(
            scene_toml=text(g.attrs.get("scene", "")),
            line_integral=images[LINE_INTEGRAL],
            inclusion_mask=images[INCLUSION_MASK],
            steps=chosen,
            displacement=fields,
            defects=defects,
            initial_gap_mm=_number(path, g, "initial_gap_mm"),
            seconds={k[len("seconds_") :]: _number(path, g, k) for k in g.attrs if k.startswith("seconds_")},
            **curve,
        )


def _read_curve(path, numbers, budget) -> dict:
    """The force-compression curve: one value per step in each series, ratio and gap finite."""
    curve = {}
    for name in CURVE:
        ds = numbers(name, (1,))
        curve[name] = budget.read(ds)
        if len(curve[name]) != len(curve[CURVE[0]]):
            raise FormatError(
                path,
                f"/{SIMULATION}/{name} holds {len(curve[name])} values, "
                f"/{SIMULATION}/{CURVE[0]} {len(curve[CURVE[0]])}: one per step in each",
            )
        if name in ("ratio", "gap_mm"):
            check_finite(path, ds.name.lstrip("/"), curve[name])
    return curve


def _read_images(path, numbers, n_steps, chosen, budget) -> dict:
    """The line integral and inclusion mask of the ``chosen`` steps (one image per step, same shape)."""
    images, first = {}, None
    for name in (LINE_INTEGRAL, INCLUSION_MASK):
        ds = numbers(name, (3,))
        if ds.shape[0] != n_steps or first not in (None, ds.shape):
            raise FormatError(
                path,
                f"/{ds.name.lstrip('/')} is {ds.shape}; expected one image per step of the "
                f"curve ({n_steps})" + (f", as /{SIMULATION}/{LINE_INTEGRAL} {first}" if first else ""),
            )
        shape = first = ds.shape
        budget.reserve(
            len(chosen) * math.prod(shape[1:]) * ds.dtype.itemsize,
            f"{len(chosen)} step(s) of /{ds.name.lstrip('/')} {shape}",
        )
        images[name] = np.stack([ds[s - 1] for s in chosen]) if chosen else ds[:0]
    return images


def _number(path, group, key) -> float:
    """A number attribute (NaN where absent)."""
    value = group.attrs.get(key, math.nan)
    if np.ndim(value) != 0 or np.asarray(value).dtype.kind not in "iuf":
        raise FormatError(path, f"{group.name}@{key} is {value!r}; expected a number")
    return float(value)
