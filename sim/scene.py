"""Scenes as data: what is compressed, how, and how it is imaged. TOML in, TOML out.

Coordinates are millimetres, the compression axis is ``y`` and the plates are normal to it.
``seed-breast``: the hemi-ellipsoid's flat face is the chest wall ``x = 0`` (sliding), the body
extends to ``x = a``; the beam is parallel along ``y`` (through the plates, as in mammography).
``pva-phantom``: the cone's axis is ``y`` (bottom face at ``y = -h/2``), compressed axially, and
imaged by a cone beam from the side along ``z`` by default. The paper does not state the beam
direction for its phantom (it says "x-ray mammogram setup", and its figures show the least
compressed image brightest and the most compressed with the most contrast): :func:`with_view`
(or ``[beam] direction = "through_plates"``) images any scene through the plates instead.

Units in names: ``_mm``, ``_kpa``, ``_per_cm``, ``_kv``, ``_ua``. Internally the mechanics works in
mm, N and MPa (N/mm^2).
"""

from __future__ import annotations

import dataclasses
import itertools
import math
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import tomli_w

from radiokit.checks import is_integer, is_number, toml_loads

__all__ = [
    "Material",
    "Body",
    "Inclusion",
    "Compression",
    "Beam",
    "Detector",
    "Exposure",
    "MeshSpec",
    "Imaging",
    "Scene",
    "load_scene",
    "anode_for",
    "block_scene",
    "with_view",
    "with_imaging",
    "with_binning",
    "PRESETS",
    "VIEWS",
    "IMAGING_MODELS",
]

GEOMETRIES = ("hemi-ellipsoid", "ellipsoid", "truncated-cone", "cylinder", "box")


def _positive(what: str, value, n: int | None = None, *, zero=False):
    """Refuse a size that is not finite and > 0 (``zero``: >= 0), or not ``n`` of them."""
    values = tuple(value) if n is not None else (value,)
    if n is not None and len(values) != n:
        raise ValueError(f"{what} {list(values)}: expected {n} numbers")
    if not all(math.isfinite(v) and (v >= 0 if zero else v > 0) for v in values):
        shown = list(values) if n is not None else value
        raise ValueError(f"{what} {shown}: expected finite numbers {'>= 0' if zero else '> 0'}")


#: Young's moduli a material may have, kPa: from a 10 Pa gel (the softest hydrogels that hold a
#: shape; brain is 0.1-1 kPa, fat 0.5-3 kPa, the gels here 5-134 kPa) to 500 GPa, above tungsten's
#: 411 GPa, the stiffest marker metal (steel 200 GPa). Past either end the number is a unit slip
#: (1e9 kPa is diamond's TPa, 1e-9 kPa a micropascal), and the solver's stiffness contrast with
#: the gels (the residual test scales with the background's modulus) is beyond what it resolves.
E_RANGE_KPA = (1e-2, 5e8)
#: Linear attenuation a material may have, per cm: lead at 20 keV, the softest line the 20-100 kVp
#: tube gives in quantity, is about 980 /cm and tungsten 1270 /cm (NIST XCOM, 86 and 66 cm^2/g);
#: at 1e4 /cm a millimetre passes e^-1000 of the beam, so no greater value changes an image.
ATTENUATION_MAX_PER_CM = 1e4


def _check_moduli(m) -> None:
    """Refuse a Young's modulus outside :data:`E_RANGE_KPA` (given, or implied by mu and kappa)."""
    lo, hi = E_RANGE_KPA
    if m.E_kpa is not None:
        if not lo <= m.E_kpa <= hi:
            raise ValueError(
                f"material {m.name!r}: E_kpa {m.E_kpa:g}: outside {lo:g}-{hi:g} kPa (a 10 Pa gel to tungsten)"
            )
        return
    E = 9 * m.kappa_kpa * m.mu_kpa / (3 * m.kappa_kpa + m.mu_kpa)
    if not lo <= E <= hi:
        raise ValueError(
            f"material {m.name!r}: mu_kpa {m.mu_kpa:g}, kappa_kpa {m.kappa_kpa:g}: Young's modulus {E:.2g} "
            f"outside {lo:g}-{hi:g} kPa (a 10 Pa gel to tungsten)"
        )


#: ``neo-hookean``: FEBio's coupled form; ``neo-hookean-uncoupled``: ANSYS's (the paper's package),
#: mu/2 (J^-2/3 I1 - 3) + kappa/2 (J - 1)^2; ``linear``: Hooke on the Green-Lagrange strain (St
#: Venant-Kirchhoff), as a geometrically nonlinear code treats a linear material.
MATERIAL_MODELS = ("neo-hookean", "neo-hookean-uncoupled", "linear")


@dataclass
class Material:
    """A hyperelastic (neo-Hookean, FEBio's form) or linear elastic solid with an attenuation.

    Give either ``E_kpa`` and ``nu`` or ``mu_kpa`` and ``kappa_kpa`` (shear and bulk moduli).
    ``psi = mu/2 (I1 - 3) - mu ln J + lambda/2 (ln J)^2``; ``"linear"`` is Hooke's law on the
    Green-Lagrange strain (St Venant-Kirchhoff, see ``MATERIAL_MODELS``).
    """

    name: str = "material"
    model: str = "neo-hookean"
    E_kpa: float | None = None
    nu: float | None = None
    mu_kpa: float | None = None
    kappa_kpa: float | None = None
    attenuation_per_cm: float = 0.5

    def __post_init__(self):
        if self.model not in MATERIAL_MODELS:
            raise ValueError(f"material {self.name!r}: model {self.model!r} is not one of {', '.join(MATERIAL_MODELS)}")
        if self.E_kpa is not None and self.nu is not None:
            if not (0 < self.E_kpa < math.inf and -1 < self.nu < 0.5):
                raise ValueError(
                    f"material {self.name!r}: need E > 0 and -1 < nu < 0.5, got {self.E_kpa}, {self.nu} "
                    "(the energies are compressible: a nearly incompressible gel is nu = 0.495)"
                )
        elif self.mu_kpa is not None and self.kappa_kpa is not None:
            if not (0 < self.mu_kpa < math.inf and 0 < self.kappa_kpa < math.inf):
                raise ValueError(
                    f"material {self.name!r}: need finite mu, kappa > 0, got {self.mu_kpa}, {self.kappa_kpa}"
                )
        else:
            raise ValueError(f"material {self.name!r}: give E_kpa and nu, or mu_kpa and kappa_kpa")
        given = [k for k in ("E_kpa", "nu", "mu_kpa", "kappa_kpa") if getattr(self, k) is not None]
        if len(given) != 2:  # the properties below read one pair: the other would be ignored
            raise ValueError(f"material {self.name!r}: give E_kpa and nu, or mu_kpa and kappa_kpa, not {given}")
        if not 0 <= self.attenuation_per_cm < math.inf:
            raise ValueError(f"material {self.name!r}: attenuation must be finite and >= 0")
        _check_moduli(self)
        if self.attenuation_per_cm > ATTENUATION_MAX_PER_CM:
            raise ValueError(
                f"material {self.name!r}: attenuation_per_cm {self.attenuation_per_cm:g}: outside "
                f"0-{ATTENUATION_MAX_PER_CM:g} per cm (lead at 20 keV is about 980)"
            )

    @property
    def shear_kpa(self) -> float:
        if self.mu_kpa is not None:
            return float(self.mu_kpa)
        return self.E_kpa / (2 * (1 + self.nu))

    @property
    def lame_kpa(self) -> float:
        """First Lamé parameter lambda = kappa - 2 mu / 3."""
        if self.mu_kpa is not None:
            return self.kappa_kpa - 2 * self.mu_kpa / 3
        return self.E_kpa * self.nu / ((1 + self.nu) * (1 - 2 * self.nu))

    @property
    def attenuation_per_mm(self) -> float:
        return self.attenuation_per_cm / 10.0


#: The sizes each body geometry reads (the others are kept but unused).
_BODY_SIZES = {
    "hemi-ellipsoid": ("semi_axes_mm",),
    "ellipsoid": ("semi_axes_mm",),
    "truncated-cone": ("height_mm", "bottom_diameter_mm", "top_diameter_mm"),
    "cylinder": ("height_mm", "diameter_mm"),
    "box": ("size_mm",),
}


@dataclass
class Body:
    """The bulk of the phantom.

    ``hemi-ellipsoid``/``ellipsoid``: ``semi_axes_mm`` (a along x, b along y, c along z); the
    hemi-ellipsoid is the half ``x >= 0``. ``truncated-cone``: ``height_mm``,
    ``bottom_diameter_mm`` (at ``y = -h/2``), ``top_diameter_mm``. ``cylinder``: ``height_mm``,
    ``diameter_mm``. ``box``: ``size_mm`` (x, y, z). All centred on the origin (the
    hemi-ellipsoid's flat face on ``x = 0``).
    """

    geometry: str = "box"
    semi_axes_mm: tuple = (25.0, 25.0, 25.0)
    height_mm: float = 60.0
    bottom_diameter_mm: float = 40.0
    top_diameter_mm: float = 50.0
    diameter_mm: float = 50.0
    size_mm: tuple = (10.0, 10.0, 10.0)
    material: Material = field(default_factory=Material)

    def __post_init__(self):
        if self.geometry not in GEOMETRIES:
            raise ValueError(f"body geometry {self.geometry!r}: expected one of {GEOMETRIES}")
        for name in _BODY_SIZES[self.geometry]:
            _positive(
                f"{self.geometry} body {name}", getattr(self, name), 3 if name in ("semi_axes_mm", "size_mm") else None
            )

    @property
    def half_height_mm(self) -> float:
        """Half the initial plate gap: the body's extent along y."""
        g = self.geometry
        if g in ("hemi-ellipsoid", "ellipsoid"):
            return float(self.semi_axes_mm[1])
        if g in ("truncated-cone", "cylinder"):
            return self.height_mm / 2
        return self.size_mm[1] / 2

    @property
    def axisymmetric(self) -> bool:
        """Rotationally symmetric about y."""
        g = self.geometry
        return g in ("truncated-cone", "cylinder") or (
            g == "ellipsoid" and self.semi_axes_mm[0] == self.semi_axes_mm[2]
        )

    def half_extent_mm(self, axis: str) -> float:
        """How far the body reaches from the origin along ``axis`` (either way)."""
        g, k = self.geometry, "xyz".index(axis)
        if g in ("hemi-ellipsoid", "ellipsoid"):
            return float(self.semi_axes_mm[k])
        if g == "box":
            return self.size_mm[k] / 2
        if axis == "y":
            return self.height_mm / 2
        return (self.diameter_mm if g == "cylinder" else max(self.bottom_diameter_mm, self.top_diameter_mm)) / 2

    def contains(self, points) -> np.ndarray:
        """Which of ``points`` (n, 3) mm lie strictly inside the body (not on its surface)."""
        p = np.asarray(points, float).reshape(-1, 3)
        x, y, z = p.T
        g = self.geometry
        if g == "box":
            return np.all(np.abs(p) < np.asarray(self.size_mm) / 2, axis=1)
        if g in ("hemi-ellipsoid", "ellipsoid"):
            inside = ((p / np.asarray(self.semi_axes_mm)) ** 2).sum(axis=1) < 1
            return inside & (x > 0) if g == "hemi-ellipsoid" else inside
        h = self.height_mm / 2
        if g == "cylinder":
            radius = self.diameter_mm / 2
        else:  # the radius grows linearly from the bottom face (y = -h) to the top (y = h)
            r1, r2 = self.bottom_diameter_mm / 2, self.top_diameter_mm / 2
            radius = r1 + (r2 - r1) * (y + h) / (2 * h)
        return (np.hypot(x, z) < radius) & (np.abs(y) < h)

    def volume_mm3(self) -> float:
        g = self.geometry
        if g == "ellipsoid":
            a, b, c = self.semi_axes_mm
            return 4 / 3 * math.pi * a * b * c
        if g == "hemi-ellipsoid":
            a, b, c = self.semi_axes_mm
            return 2 / 3 * math.pi * a * b * c
        if g == "truncated-cone":
            r1, r2 = self.bottom_diameter_mm / 2, self.top_diameter_mm / 2
            return math.pi * self.height_mm / 3 * (r1 * r1 + r1 * r2 + r2 * r2)
        if g == "cylinder":
            return math.pi * (self.diameter_mm / 2) ** 2 * self.height_mm
        return float(self.size_mm[0] * self.size_mm[1] * self.size_mm[2])


@dataclass
class Inclusion:
    """A region of another material strictly inside the body (stiffer, as a tumour, or softer):
    ``sphere`` (``diameter_mm``) or ``box`` (``size_mm``, axis-aligned), at ``centre_mm``."""

    shape: str = "sphere"
    centre_mm: tuple = (0.0, 0.0, 0.0)
    diameter_mm: float = 8.0
    size_mm: tuple = (8.0, 10.0, 8.0)
    material: Material = field(
        default_factory=lambda: Material("inclusion", "linear", E_kpa=30, nu=0.495, attenuation_per_cm=1.0)
    )

    def __post_init__(self):
        if self.shape not in ("sphere", "box"):
            raise ValueError(f"inclusion shape {self.shape!r}: expected 'sphere' or 'box'")
        if len(self.centre_mm) != 3 or not all(math.isfinite(v) for v in self.centre_mm):
            raise ValueError(f"inclusion centre_mm {list(self.centre_mm)}: expected 3 finite numbers")
        if self.shape == "sphere":
            _positive("sphere inclusion diameter_mm", self.diameter_mm)
        else:
            _positive("box inclusion size_mm", self.size_mm, 3)

    def volume_mm3(self) -> float:
        if self.shape == "sphere":
            return math.pi / 6 * self.diameter_mm**3
        return float(self.size_mm[0] * self.size_mm[1] * self.size_mm[2])


@dataclass
class Compression:
    """Rigid plates normal to y, closing to ``1 - ratio`` of the initial gap, one state per
    ratio: strictly increasing, each in [0, 0.9) (0 is the uncompressed reference).

    Which plate moves depends on the model: where it is cut at y = 0 (body and inclusions
    symmetric in y, ``MeshSpec.symmetry`` on) both close by half the step and the centre plane
    stays; otherwise (the truncated cone, an inclusion off the centre plane, symmetry off) the
    bottom plate stays and the top one closes the whole step, as the paper's phantom frame does
    ("a movable plate"). Between frictionless plates the two differ by a rigid shift of half the
    step along y, nothing else (tests/test_sim_mechanics.py)."""

    ratios: tuple = (0.15, 0.20, 0.25)
    contact: str = "frictionless"

    def __post_init__(self):
        if self.contact not in ("frictionless", "bonded"):
            raise ValueError(f"contact {self.contact!r}: expected 'frictionless' or 'bonded'")
        if not self.ratios:
            raise ValueError("compression ratios: none given")
        if not all(0 <= r < 0.9 for r in self.ratios):
            raise ValueError(f"compression ratios {list(self.ratios)} must lie in [0, 0.9)")
        # one state per ratio, in the order given: a repeated ratio would silently give one state
        # fewer, a decreasing one would be reordered (the plates only close)
        if any(b <= a for a, b in zip(self.ratios, self.ratios[1:])):
            raise ValueError(f"compression ratios {list(self.ratios)} must increase strictly")


#: The two imaging geometries, by the beam direction: through the plates (along the compression
#: axis y, as in mammography) or from the side (along z, across the compression axis).
VIEWS = {"through_plates": "y", "side": "z"}


#: The farthest a cone beam's source or detector may be from the body, mm: a room's length (the
#: lab's cabinet is under 1.5 m). At 10 m the magnification of a body 100 mm before the
#: detector is 1.01 and the rays over the 112 mm field diverge by 0.3 degrees: a parallel beam.
DISTANCE_MAX_MM = 1e4


@dataclass
class Beam:
    """``parallel`` or ``cone`` beam along ``direction``: ``"y"`` (alias ``"through_plates"``)
    or ``"z"`` (alias ``"side"``); aliases are stored as the axis. Cone beams have the source
    ``source_distance_mm`` before the body's centre and the detector ``detector_distance_mm``
    behind it (magnification (s + d) / s)."""

    kind: str = "parallel"
    direction: str = "y"
    source_distance_mm: float = 500.0
    detector_distance_mm: float = 100.0

    def __post_init__(self):
        if self.kind not in ("parallel", "cone"):
            raise ValueError(f"beam kind {self.kind!r}: expected 'parallel' or 'cone'")
        self.direction = VIEWS.get(self.direction, self.direction)
        if self.direction not in ("y", "z"):
            raise ValueError(f"beam direction {self.direction!r}: expected 'y' (through_plates) or 'z' (side)")
        _positive("beam source_distance_mm", self.source_distance_mm)
        _positive("beam detector_distance_mm", self.detector_distance_mm, zero=True)
        for name in ("source_distance_mm", "detector_distance_mm"):
            if getattr(self, name) > DISTANCE_MAX_MM:
                raise ValueError(
                    f"beam {name} {getattr(self, name):g}: expected at most {DISTANCE_MAX_MM:g} mm "
                    "(a room's length; a source farther than that is a parallel beam: kind = 'parallel')"
                )

    @property
    def view(self) -> str:
        """``through_plates`` (beam along y) or ``side`` (along z)."""
        return "through_plates" if self.direction == "y" else "side"

    @property
    def magnification(self) -> float:
        if self.kind == "parallel":
            return 1.0
        return (self.source_distance_mm + self.detector_distance_mm) / self.source_distance_mm


@dataclass
class Detector:
    """A C7942 preset (``radiokit.io.PRESETS``) at ``binning`` 1, 2 or 4."""

    preset: str = "c7942"
    binning: int = 1

    def __post_init__(self):
        from radiokit.io import PRESETS

        if self.preset not in PRESETS or PRESETS[self.preset].binning != 1:
            raise ValueError(
                f"detector preset {self.preset!r}: expected an unbinned preset "
                f"({', '.join(k for k, v in PRESETS.items() if v.binning == 1)}); set binning separately"
            )
        if self.binning not in (1, 2, 4):
            raise ValueError(f"binning {self.binning}: expected 1, 2 or 4")

    @property
    def shape(self) -> tuple[int, int]:
        from radiokit.io import PRESETS

        p = PRESETS[self.preset]
        return (p.rows // self.binning, p.cols // self.binning)

    @property
    def pixel_size_mm(self) -> float:
        return 0.05 * self.binning

    #: the name an experiment file of this panel's frames records
    panel_name = "Hamamatsu C7942SK-02 (simulated)"

    @property
    def pixel_size_from(self) -> str:
        """Where :attr:`pixel_size_mm` comes from, as an experiment file records it."""
        return f"the simulated detector, preset {self.preset} binned {self.binning}x{self.binning}"


#: The least open beam a pixel may collect, counts above the dark offset: one count is the 12-bit
#: ADC's least step, half the panel's read noise (2 counts) and a sixth of its dark offset's
#: spread over pixels (6); below it a flat cannot be told from a dark, and -ln(I / I0) is noise.
I0_MIN_COUNTS = 1.0


@dataclass
class Exposure:
    """The source: ``i0_counts`` is the open beam (counts above the dark offset) one *unbinned*
    50 µm pixel collects at ``voltage_kv`` and ``current_ua`` -- the dose the tube current, the
    exposure time and the distance give it, whatever the binning. A binned read-out pixel sums the
    charge of ``binning**2`` of them (:func:`sim.lab.open_beam_counts`), so binning the same source
    by 2 gives 4x the counts and twice the SNR, and may saturate the 12-bit ADC:
    :meth:`Scene.validate` refuses a scene whose binned open beam would (:func:`with_binning` lowers
    the current instead, as the lab does). kV and µA are recorded as metadata, and the kV sets the
    polychromatic spectrum. The tube's and the panel's ranges are checked by :meth:`Scene.validate`
    (they depend on the anode)."""

    i0_counts: float = 2500.0
    voltage_kv: float = 60.0
    current_ua: float = 250.0

    def __post_init__(self):
        _positive("exposure voltage_kv", self.voltage_kv)
        _positive("exposure current_ua", self.current_ua)
        _positive("exposure i0_counts", self.i0_counts)
        if self.i0_counts < I0_MIN_COUNTS:
            raise ValueError(
                f"exposure i0_counts {self.i0_counts:g}: expected at least {I0_MIN_COUNTS:g} count per pixel "
                "(the 12-bit ADC's least step: below it a flat is a dark)"
            )
        _check_open_beam(self.i0_counts, 1)  # the least any binning reads out


def _check_open_beam(i0_counts: float, binning: int) -> None:
    """ValueError unless the open beam of a read-out pixel, ``i0_counts`` per unbinned pixel summed
    over ``binning**2`` of them, keeps its brightest pixels below the 12-bit ceiling
    (:meth:`sim.detector.PanelModel.open_beam_ceiling`): beyond it the flats, and every pixel the
    object does not shade, clip at 4095, the calibration marks them defective (or refuses the flat)
    and the line integral reads low."""
    from sim.detector import PanelModel

    ceiling = PanelModel.open_beam_ceiling()
    if i0_counts * binning**2 <= ceiling:
        return
    binned = ""
    if binning > 1:
        binned = (
            f" at detector binning {binning} (a read-out pixel sums {binning**2} pixels' charge: "
            f"{i0_counts * binning**2:g} counts)"
        )
    raise ValueError(
        f"exposure i0_counts {i0_counts:g}{binned}: the open beam would saturate the C7942's 12-bit ADC "
        f"(4095 counts: about {PanelModel.dark_level:g} of dark offset, and the brightest pixels' gain "
        f"and noise above the mean): need at most {math.floor(ceiling / binning**2):d}"
        + (" (a lower tube current or a shorter exposure), or less binning" if binning > 1 else "")
    )


#: Named imaging models: ``paper`` is the paper's (a monochromatic beam, no scatter; the line
#: integral ``sum_m mu_m L_m``), ``experiment`` the cheapest whose headline numbers stay within
#: 1 % of the richest model measured (benchmarks/bench_model.py): the tube's spectrum and scatter.
IMAGING_MODELS = ("paper", "experiment")


@dataclass
class Imaging:
    """What the detector sees beyond the line integral (:mod:`sim.imaging`).

    ``beam``: ``monochromatic`` (the paper's) or ``polychromatic`` (the tube's spectrum from
    SpekPy at ``exposure.voltage_kv``, anode ``anode``: ``auto`` is molybdenum up to 35 kV, a
    mammography tube, else tungsten, the L8121-01's; water-shaped attenuation from XrayDB,
    matched to the scene's coefficients through the body's thickness along the beam
    (:func:`sim.imaging.match_thickness_mm`: the plate gap through the plates, the body's width
    from the side, the longest chord of either view). ``scatter_fraction``: scatter-to-primary
    ratio through that thickness (0: none), spread
    by a Gaussian of ``scatter_sigma_mm``; ``blur_sigma_mm``: the scintillator's point spread.
    """

    beam: str = "monochromatic"
    anode: str = "auto"
    scatter_fraction: float = 0.0
    scatter_sigma_mm: float = 10.0
    blur_sigma_mm: float = 0.0

    def __post_init__(self):
        if self.beam not in ("monochromatic", "polychromatic"):
            raise ValueError(f"imaging beam {self.beam!r}: expected 'monochromatic' or 'polychromatic'")
        if self.anode not in ("auto", "W", "Mo"):
            raise ValueError(f"imaging anode {self.anode!r}: expected 'auto', 'W' or 'Mo'")
        if not (
            0 <= self.scatter_fraction < 10
            and 0 < self.scatter_sigma_mm < math.inf
            and 0 <= self.blur_sigma_mm < math.inf
        ):
            raise ValueError("imaging: need 0 <= scatter_fraction < 10, scatter_sigma_mm > 0, blur_sigma_mm >= 0")

    @classmethod
    def named(cls, name: str) -> Imaging:
        """``paper`` or ``experiment`` (see :data:`IMAGING_MODELS`)."""
        if name == "paper":
            return cls()
        if name == "experiment":
            # SPR 0.3: a 5-6 cm object without an anti-scatter grid
            return cls("polychromatic", "auto", 0.3, 10.0, 0.0)
        raise ValueError(f"imaging model {name!r}: expected one of {', '.join(IMAGING_MODELS)}")

    @property
    def is_paper(self) -> bool:
        return self == Imaging()


@dataclass
class MeshSpec:
    """Element sizes (graded from ``size_inclusion_mm`` at the inclusion to ``size_far_mm``),
    the model (``auto`` picks axisymmetric where the scene allows it), symmetry use, and curved
    (isoparametric) quadratic elements."""

    size_inclusion_mm: float = 1.0
    size_far_mm: float = 5.0
    model: str = "auto"
    symmetry: bool = True
    curved: bool = True  #: quadratic elements follow curved surfaces (edge nodes on them)
    #: at most this size next to the plates (None: the graded sizes): where a curved body's
    #: contact patch ends, the column between the plates is only as exact as the surface there
    size_contact_mm: float | None = None

    def __post_init__(self):
        if self.model not in ("auto", "3d", "axisymmetric", "plane-strain"):
            raise ValueError(f"mesh model {self.model!r}: expected auto, 3d, axisymmetric or plane-strain")
        if not (0 < self.size_inclusion_mm <= self.size_far_mm < math.inf):
            raise ValueError(
                f"mesh sizes {self.size_inclusion_mm}, {self.size_far_mm}: need 0 < size_inclusion_mm <= size_far_mm, finite"
            )
        if self.size_contact_mm is not None and not 0 < self.size_contact_mm <= self.size_far_mm:
            raise ValueError("mesh sizes: need 0 < size_contact_mm <= size_far_mm")


@dataclass
class Scene:
    """Everything that defines one virtual experiment. ``Scene.from_toml(text)`` /
    ``scene.to_toml()`` round-trip exactly, so a result can name what produced it."""

    name: str = "scene"
    body: Body = field(default_factory=Body)
    inclusions: list = field(default_factory=list)
    compression: Compression = field(default_factory=Compression)
    beam: Beam = field(default_factory=Beam)
    detector: Detector = field(default_factory=Detector)
    exposure: Exposure = field(default_factory=Exposure)
    mesh: MeshSpec = field(default_factory=MeshSpec)
    #: beyond the line integral: the paper's monochromatic, scatter-free model unless set (the
    #: presets use the ``experiment`` model, see :class:`Imaging`)
    imaging: Imaging = field(default_factory=Imaging)
    #: The flat face x = 0 of a hemi-ellipsoid (the chest wall): ``none`` (free), ``sliding`` (held
    #: in x only, frictionless; the default for seed-breast) or ``fixed`` (no displacement: the
    #: paper's condition, singular where the plates pass the wall's rim; see sim.mechanics).
    wall: str = "none"

    def __post_init__(self):
        if self.wall not in ("none", "sliding", "fixed"):
            raise ValueError(f"wall {self.wall!r}: expected 'none', 'sliding' or 'fixed'")
        self.validate()

    def validate(self) -> Scene:
        """Refuse what each part cannot see alone: an inclusion not strictly inside the body,
        overlapping another or too small for its mesh size; a cone beam's source or detector
        inside the body; kV and µA outside the tube's or the panel's ratings; an open beam that
        would saturate the ADC once binned. Run on construction and again before meshing (a
        scene's fields may be replaced). Returns the scene."""
        for i, inc in enumerate(self.inclusions):
            where = f"inclusions[{i}] ({_describe(inc)})"
            if not self.body.contains(_hull_points(inc)).all():
                raise ValueError(
                    f"scene {self.name!r}: {where} is not strictly inside the {self.body.geometry} body "
                    "(it touches, crosses or lies outside its surface)"
                )
            for j, other in enumerate(self.inclusions[:i]):
                if _overlap(inc, other):
                    raise ValueError(f"scene {self.name!r}: {where} touches or overlaps inclusions[{j}]")
            smallest = inc.diameter_mm if inc.shape == "sphere" else min(inc.size_mm)
            if self.mesh.size_inclusion_mm > smallest / 2:
                raise ValueError(
                    f"scene {self.name!r}: mesh size_inclusion_mm {self.mesh.size_inclusion_mm:g} cannot resolve "
                    f"{where}: need at most half its smallest extent, {smallest / 2:g} mm"
                )
        if self.beam.kind == "cone":
            extent = self.body.half_extent_mm(self.beam.direction)
            for name in ("source_distance_mm", "detector_distance_mm"):
                if getattr(self.beam, name) <= extent:
                    raise ValueError(
                        f"scene {self.name!r}: beam {name} {getattr(self.beam, name):g} lies inside the body, which "
                        f"reaches {extent:g} mm from its centre along {self.beam.direction}"
                    )
        if self.body.geometry in ("ellipsoid", "hemi-ellipsoid"):
            _check_curved_contact(self)
        if self.wall != "none" and self.body.geometry != "hemi-ellipsoid":
            # the mechanics holds the plane x = 0: for any other body an interior plane
            raise ValueError(
                f"scene {self.name!r}: wall {self.wall!r} is the flat face x = 0 of a hemi-ellipsoid; "
                f"a {self.body.geometry} has none (use wall = 'none')"
            )
        _check_tube(self.exposure, self.imaging.anode)
        try:  # the binning is the detector's, the dose the exposure's: only the scene sees both
            _check_open_beam(self.exposure.i0_counts, self.detector.binning)
            _check_field_of_view(self)
            _check_image_sigmas(self)
            from sim.mesh import check_mesh_size  # late: sim.mesh imports this module

            check_mesh_size(self)
        except ValueError as exc:
            raise ValueError(f"scene {self.name!r}: {exc}") from None
        return self

    # -- TOML ---------------------------------------------------------------------------------
    def to_dict(self) -> dict:
        d = _strip_none(dataclasses.asdict(self))
        # only the sizes the body's geometry reads: a saved hemi-ellipsoid also held diameter_mm,
        # and editing it changed nothing
        unread = {n for sizes in _BODY_SIZES.values() for n in sizes} - set(_BODY_SIZES[self.body.geometry])
        d["body"] = {k: v for k, v in d["body"].items() if k not in unread}
        return d

    def to_toml(self) -> str:
        return tomli_w.dumps(self.to_dict())

    def save(self, path) -> Path:
        path = Path(path)
        path.write_text(self.to_toml())
        return path

    @classmethod
    def from_dict(cls, d: dict) -> Scene:
        d = dict(d)
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = set(d) - known
        if unknown:
            raise ValueError(f"scene: unknown keys {sorted(unknown)}; known: {sorted(known)}")
        kw = {}
        for name, typ in (
            ("body", Body),
            ("compression", Compression),
            ("beam", Beam),
            ("detector", Detector),
            ("exposure", Exposure),
            ("mesh", MeshSpec),
            ("imaging", Imaging),
        ):
            if name in d:
                kw[name] = _build(typ, d.pop(name), name)
        if "inclusions" in d:
            incs = d.pop("inclusions")
            if not isinstance(incs, list):
                raise ValueError(f"scene inclusions: expected an array of tables ([[inclusions]]), got {incs!r}")
            kw["inclusions"] = [_build(Inclusion, x, f"inclusions[{i}]") for i, x in enumerate(incs)]
        for name, value in d.items():  # name, wall
            kw[name] = _typed(value, "str", name)
        return cls(**kw)

    @classmethod
    def from_toml(cls, text: str) -> Scene:
        try:
            return cls.from_dict(toml_loads(text))
        except tomllib.TOMLDecodeError as exc:
            raise ValueError(f"scene TOML: {exc}") from exc


def _build(typ, d, where):
    if not isinstance(d, dict):
        raise ValueError(f"scene {where}: expected a table, got {d!r}")
    d = dict(d)
    types = {f.name: f.type for f in dataclasses.fields(typ) if f.init}
    unknown = set(d) - set(types)
    if unknown:
        raise ValueError(f"scene {where}: unknown keys {sorted(unknown)}; known: {sorted(types)}")
    if typ is Body and d.get("geometry", Body.geometry) in _BODY_SIZES:
        # a size the geometry does not read would be ignored in silence (a cylinder's diameter_mm
        # on a hemi-ellipsoid): refused, naming what it reads
        reads = _BODY_SIZES[d.get("geometry", Body.geometry)]
        # a file saved before saving left them out (and the @scene text of older simulated files)
        # holds every size, the unread ones at their defaults: there an edit is a value that
        # differs; elsewhere any unread size is one (a box's size_mm under geometry = "cylinder")
        every = {k for sizes in _BODY_SIZES.values() for k in sizes}
        default = {f.name: f.default for f in dataclasses.fields(Body)} if every <= set(d) else {}
        unread = sorted(
            {
                k
                for sizes in _BODY_SIZES.values()
                for k in sizes
                if k in d and k not in reads and _as_tuple(d[k]) != default.get(k, object())
            }
        )
        if unread:
            raise ValueError(
                f"scene {where}: {', '.join(unread)} not read by a {d.get('geometry', Body.geometry)} body "
                f"(it reads {', '.join(reads)})"
            )
    for k, v in d.items():
        if k == "material":
            d[k] = _build(Material, v, f"{where}.material")
        else:
            d[k] = _typed(v, types[k], f"{where}.{k}")
    try:
        return typ(**d)
    except ValueError as exc:  # the dataclass names the field; this names where it is in the file
        raise ValueError(f"scene {where}: {exc}") from None


def _as_tuple(value):
    return tuple(value) if isinstance(value, list) else value


def _typed(value, annotation: str, where: str):
    """``value`` as the field's type (the annotation's text: ``from __future__ import annotations``)
    or a ValueError naming the key: TOML's types are not Python's (an integer where a number is
    meant is fine, a string or a boolean is not; ``True > 0`` would pass a range check)."""
    kind = annotation.split(" | ")[0]
    if kind == "float" and is_number(value):
        return float(value)
    if kind == "int" and is_integer(value):
        return int(value)  # a numpy integer (the Python API) is not TOML's
    if kind == "str" and isinstance(value, str) or kind == "bool" and isinstance(value, bool):
        return value
    if kind == "tuple" and isinstance(value, (list, tuple)) and all(is_number(v) for v in value):
        return tuple(float(v) for v in value)
    expected = {"float": "a number", "int": "an integer", "str": "a string", "bool": "true or false"}
    raise ValueError(f"scene {where}: expected {expected.get(kind, 'a list of numbers')}, got {value!r}")


def _check_curved_contact(scene: Scene):
    """A curved body meets the plates by penalty contact, solved on its half y >= 0 with the
    other plate mirrored (sim.mechanics): frictionless, and the scene symmetric about y = 0."""
    name, g = scene.name, scene.body.geometry
    if scene.compression.contact == "bonded":
        raise ValueError(
            f"scene {name!r}: bonded plates need flat faces on the plates; a {g} touches them at a point "
            "(use contact = 'frictionless')"
        )
    if not scene.mesh.symmetry:
        raise ValueError(f"scene {name!r}: a {g} is solved on its half y >= 0: set mesh.symmetry = true")
    for i, inc in enumerate(scene.inclusions):
        if inc.centre_mm[1] != 0:
            raise ValueError(
                f"scene {name!r}: inclusions[{i}] is centred at y = {inc.centre_mm[1]:g} mm; a {g} is solved "
                "on its half y >= 0, so its inclusions must be centred at y = 0"
            )


def _hull_points(inc: Inclusion) -> np.ndarray:
    """Points whose convex hull contains the inclusion: all bodies are convex, so the inclusion
        is strictly inside one when these points are. A box's corners; for a sphere, 2000 Fibonacci
        points on a sphere 1 % larger (their hull's facets lie 0.998 of that radius from the centre,
    outside the inclusion: tests/test_sim_scene_checks.py)."""
    c = np.asarray(inc.centre_mm, float)
    if inc.shape == "box":
        return c + np.asarray(inc.size_mm) / 2 * np.array(list(itertools.product((-1.0, 1.0), repeat=3)))
    n = 2000
    k = np.arange(n) + 0.5
    z = 1 - 2 * k / n
    phi = math.pi * (1 + math.sqrt(5)) * k
    r = np.sqrt(1 - z * z)
    return c + 1.01 * inc.diameter_mm / 2 * np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def _overlap(a: Inclusion, b: Inclusion) -> bool:
    """Whether two inclusions touch or overlap (exact for spheres and axis-aligned boxes)."""
    if a.shape == "box" and b.shape == "box":
        gap = np.abs(np.subtract(a.centre_mm, b.centre_mm)) - (np.asarray(a.size_mm) + b.size_mm) / 2
        return bool(np.all(gap <= 0))
    if a.shape == "box":
        a, b = b, a
    c = np.asarray(a.centre_mm, float)
    if b.shape == "sphere":
        return float(np.linalg.norm(c - b.centre_mm)) <= (a.diameter_mm + b.diameter_mm) / 2
    half = np.asarray(b.size_mm) / 2
    nearest = np.clip(c, np.subtract(b.centre_mm, half), np.add(b.centre_mm, half))
    return float(np.linalg.norm(c - nearest)) <= a.diameter_mm / 2


def _describe(inc: Inclusion) -> str:
    size = (
        f"diameter {inc.diameter_mm:g} mm"
        if inc.shape == "sphere"
        else "size " + " x ".join(f"{v:g}" for v in inc.size_mm) + " mm"
    )
    return f"{inc.shape}, {size}, centre {', '.join(f'{v:g}' for v in inc.centre_mm)} mm"


#: The panel: C7942 "-02" models are specified for 20-100 kVp (../shared/hardware/C7942.md).
PANEL_KV = (20.0, 100.0)
#: The L8121-01 (tungsten anode): 40-150 kV, up to 500 uA, 75 W (../shared/hardware/L8121.md).
#: Within the panel's 100 kV, 500 uA is at most 50 W: the power rating cannot bind.
L8121_KV, L8121_UA = (40.0, 150.0), 500.0
#: ``anode = "auto"``: molybdenum (a mammography tube) up to this voltage, else the L8121-01.
AUTO_MO_MAX_KV = 35.0


def anode_for(voltage_kv: float, anode: str) -> str:
    """The anode a scene's tube has: ``W`` (the L8121-01) or ``Mo`` (a mammography tube)."""
    if anode == "auto":
        return "Mo" if voltage_kv <= AUTO_MO_MAX_KV else "W"
    return anode


def _check_tube(ex: Exposure, anode: str):
    kv, ua = ex.voltage_kv, ex.current_ua
    if not PANEL_KV[0] <= kv <= PANEL_KV[1]:
        raise ValueError(f"exposure voltage_kv {kv:g}: outside the C7942's rated {PANEL_KV[0]:g}-{PANEL_KV[1]:g} kVp")
    if anode_for(kv, anode) == "W":
        how = f"imaging anode {anode!r}" + (f", which is W above {AUTO_MO_MAX_KV:g} kV" if anode == "auto" else "")
        if not L8121_KV[0] <= kv <= L8121_KV[1]:
            raise ValueError(
                f"exposure voltage_kv {kv:g}: the L8121-01 (tungsten anode; {how}) runs "
                f"{L8121_KV[0]:g}-{L8121_KV[1]:g} kV"
            )
        if ua > L8121_UA:
            raise ValueError(f"exposure current_ua {ua:g}: the L8121-01 gives at most {L8121_UA:g} µA")


#: The body field that sets its width along each axis, by geometry.
_WIDTH_FIELDS = {
    "hemi-ellipsoid": {"x": "semi_axes_mm", "y": "semi_axes_mm", "z": "semi_axes_mm"},
    "ellipsoid": {"x": "semi_axes_mm", "y": "semi_axes_mm", "z": "semi_axes_mm"},
    "box": {"x": "size_mm", "y": "size_mm", "z": "size_mm"},
    "cylinder": {"x": "diameter_mm", "y": "height_mm", "z": "diameter_mm"},
    "truncated-cone": {"x": "bottom_diameter_mm", "y": "height_mm", "z": "bottom_diameter_mm"},
}


def _field_of_view(scene: Scene) -> dict:
    """The detector's field of view at the isocentre (mm) along the two axes across the beam:
    columns follow x, rows z (beam along y) or y (beam along z) (sim.xray's detector frame)."""
    rows, cols = scene.detector.shape
    p, m = scene.detector.pixel_size_mm, scene.beam.magnification
    return {"x": (cols, cols * p / m), ("z" if scene.beam.direction == "y" else "y"): (rows, rows * p / m)}


def _check_field_of_view(scene: Scene) -> None:
    """Refuse a body wider than the detector sees: the simulated experiment images the whole body
    (the beam is matched, and scatter referred, to its thickness). A semi-axis of 1e9 mm reached
    the projection and ended in numpy's "zero-size array to reduction operation" (review s41cli)."""
    b = scene.body
    for axis, (n, fov) in _field_of_view(scene).items():
        width = b.half_extent_mm(axis) * (1 if b.geometry == "hemi-ellipsoid" and axis == "x" else 2)
        if width <= fov:
            continue
        name = _WIDTH_FIELDS[b.geometry][axis]
        if b.geometry == "truncated-cone" and name == "bottom_diameter_mm" and b.top_diameter_mm > b.bottom_diameter_mm:
            name = "top_diameter_mm"
        value = getattr(b, name)
        shown = "[" + ", ".join(f"{v:g}" for v in value) + "]" if isinstance(value, tuple) else f"{value:g}"
        at = "" if scene.beam.magnification == 1 else f" at magnification {scene.beam.magnification:g}"
        raise ValueError(
            f"body {name} {shown}: {width:g} mm along {axis}, wider than the detector's {fov:g} mm field of view "
            f"there ({n} pixels of {scene.detector.pixel_size_mm:g} mm{at})"
        )


def _check_image_sigmas(scene: Scene) -> None:
    """Refuse a scatter or blur spread wider than the image: it would spread every pixel over the
    whole detector and more (1e9 mm allocated "array is too big" after 37-52 s of mechanics)."""
    rows, cols = scene.detector.shape
    p = scene.detector.pixel_size_mm
    side = max(rows, cols) * p
    for name in ("scatter_sigma_mm", "blur_sigma_mm"):
        value = getattr(scene.imaging, name)
        if value > side:
            raise ValueError(
                f"imaging {name} {value:g}: expected at most the image's {side:g} mm "
                f"(its larger side: {max(rows, cols)} pixels of {p:g} mm)"
            )


def _strip_none(obj):
    if isinstance(obj, dict):
        return {k: _strip_none(v) for k, v in obj.items() if v is not None}
    if isinstance(obj, (list, tuple)):
        return [_strip_none(v) for v in obj]
    return obj


# -- presets -----------------------------------------------------------------------------------
def _seed_breast() -> Scene:
    background = Material("breast tissue", "neo-hookean", E_kpa=5.0, nu=0.495, attenuation_per_cm=0.5)
    tumour = Material("tumour", "linear", E_kpa=30.0, nu=0.495, attenuation_per_cm=1.0)
    return Scene(
        name="seed-breast",
        body=Body("hemi-ellipsoid", semi_axes_mm=(50.0, 25.0, 25.0), material=background),
        inclusions=[Inclusion("sphere", centre_mm=(25.0, 0.0, 0.0), diameter_mm=8.0, material=tumour)],
        compression=Compression((0.15, 0.20, 0.25)),
        beam=Beam("parallel", "y"),
        detector=Detector("c7942", 1),
        exposure=Exposure(2500.0, 28.0, 250.0),
        # within 2 % of its double (0.7 / 6 / 1.0 mm) in force, inclusion strain, change ratio and
        # IF: the band at the plates, not the inclusion, sets the headline (README, convergence)
        mesh=MeshSpec(1.4, 12.0, "3d", True, size_contact_mm=2.0),
        imaging=Imaging.named("experiment"),
        wall="sliding",
    )


# PVA gels stiffen with strain: E rises from ~20 to ~30 kPa (10 % w/v) and ~100 to ~250 kPa
# (20 % w/v) over 0-20 % strain. sim.materials.fit_neo_hookean gives the neo-Hookean E0 whose
# tangent modulus is closest (log least squares) to each ramp: 19.7 kPa (misfit <= 7.5 %) and
# 134 kPa (misfit <= 34 %: a neo-Hookean solid stiffens 1.64x over 20 %, not 2.5x).
def _pva_phantom() -> Scene:
    gel = Material("PVA 10 % w/v", "neo-hookean", E_kpa=19.7, nu=0.495, attenuation_per_cm=0.77)
    stiff = Material("PVA 20 % w/v", "neo-hookean", E_kpa=134.0, nu=0.495, attenuation_per_cm=0.85)
    return Scene(
        name="pva-phantom",
        body=Body("truncated-cone", height_mm=60.0, bottom_diameter_mm=40.0, top_diameter_mm=50.0, material=gel),
        inclusions=[Inclusion("box", centre_mm=(0.0, 0.0, 0.0), size_mm=(8.0, 10.0, 8.0), material=stiff)],
        compression=Compression((0.15, 0.20, 0.25)),
        beam=Beam("cone", "z", source_distance_mm=400.0, detector_distance_mm=100.0),
        detector=Detector("c7942", 1),
        exposure=Exposure(2500.0, 60.0, 250.0),
        mesh=MeshSpec(1.0, 5.0, "3d", True),
        imaging=Imaging.named("experiment"),
    )


PRESETS = {"seed-breast": _seed_breast, "pva-phantom": _pva_phantom}


def load_scene(name_or_toml) -> Scene:
    """A preset by name (``seed-breast``, ``pva-phantom``), a TOML file, or TOML text."""
    if isinstance(name_or_toml, Scene):
        return name_or_toml
    text = str(name_or_toml)
    if text in PRESETS:
        return PRESETS[text]()
    path = Path(text)
    if "\n" not in text and path.suffix == ".toml" or _names_a_file(text):
        if path.is_dir():
            raise ValueError(f"{path}: is a folder, not a scene file (presets: {', '.join(PRESETS)})")
        if not path.exists():
            raise FileNotFoundError(f"{path}: no such scene file (presets: {', '.join(PRESETS)})")
        try:
            return Scene.from_toml(path.read_text())
        except UnicodeDecodeError:  # an experiment file or an image given for the scene
            raise ValueError(f"{path}: not TOML text (binary data): not a scene file") from None
        except ValueError as exc:
            raise ValueError(f"{path}: {exc}") from exc
    if "=" in text or "[" in text:
        return Scene.from_toml(text)
    raise ValueError(f"unknown scene {text!r}: a preset ({', '.join(PRESETS)}), a .toml file or TOML text")


def _names_a_file(text: str) -> bool:
    """One line naming something on disk (a folder, a scene file not named .toml, an experiment
    file given by mistake): named as such, not as an unknown scene or TOML text."""
    if "\n" in text or "=" in text:
        return False
    try:
        return Path(text).exists()
    except (OSError, ValueError):  # too long or not a path at all: not a file
        return False


def with_view(scene: Scene, view: str) -> Scene:
    """A copy of ``scene`` imaged ``through_plates`` (beam along y) or from the ``side`` (along z),
    everything else (beam kind, distances, detector) kept; the name gains the view."""
    if view not in VIEWS:
        raise ValueError(f"view {view!r}: expected one of {', '.join(VIEWS)}")
    beam = dataclasses.replace(scene.beam, direction=VIEWS[view])
    name = scene.name if scene.beam.direction == beam.direction else f"{scene.name}-{view.replace('_', '-')}"
    return dataclasses.replace(scene, name=name, beam=beam)


def with_imaging(scene: Scene, model: str) -> Scene:
    """A copy of ``scene`` seen through the named imaging model (``paper``: monochromatic, no
    scatter; ``experiment``: the tube's spectrum and scatter), everything else kept."""
    return dataclasses.replace(scene, imaging=Imaging.named(model))


def with_binning(scene: Scene, binning: int) -> Scene:
    """A copy of ``scene`` read out at ``binning`` whose read-out pixels keep the open beam the
    scene gives them: the tube current, and with it the dose per unbinned pixel (``i0_counts``),
    scaled by the change in binned area -- what the lab does when it bins, since a binned pixel
    sums ``binning**2`` pixels' charge and the same current would saturate the 12-bit ADC. A
    quarter of the current at 2x2 from 1x1; kV, geometry and everything else are kept."""
    detector = Detector(scene.detector.preset, binning)  # refuses a binning the C7942 lacks
    k = (scene.detector.binning / detector.binning) ** 2
    ex = scene.exposure
    exposure = dataclasses.replace(ex, i0_counts=ex.i0_counts * k, current_ua=ex.current_ua * k)
    return dataclasses.replace(scene, detector=detector, exposure=exposure)


def block_scene(size_mm=10.0, E_kpa=5.0, nu=0.45, ratios=(0.15, 0.20, 0.25)) -> Scene:
    """A cube between frictionless plates, no inclusion: the validation scene with a closed form."""
    return Scene(
        name="block",
        body=Body(
            "box", size_mm=(size_mm, size_mm, size_mm), material=Material("block", "neo-hookean", E_kpa=E_kpa, nu=nu)
        ),
        compression=Compression(tuple(ratios)),
        beam=Beam("parallel", "y"),
        detector=Detector("c7942", 4),
        # 2500 counts per 4x4 read-out pixel (the default exposure's at 1x1) at 60 kV, 250 µA:
        # 2500 / 16 per unbinned pixel
        exposure=Exposure(2500.0 / 16, 60.0, 250.0),
        mesh=MeshSpec(size_mm / 4, size_mm / 4, "3d", True),
    )
