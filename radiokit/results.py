"""The numbers and images of one processed experiment as typed records, and their one serialisation.

:func:`radiokit.pipeline.process` builds a :class:`Results`; ``results.json`` is
:meth:`Results.to_json` with a ``schema_version``, and :func:`load_results` reads it back into
the same records (refusing a file of an unknown major version). The layout of the JSON is the
one radiokit has always written: per domain, per k keyed by :func:`k_label` (``"1"``, ``"2"``),
per step pair keyed ``"a->b"``.

k values are floats everywhere in memory; :func:`k_label` is the only place they become text
(JSON keys, HDF5 dataset names).

A zero reference contrast makes the improvement factor undefined: the pipeline refuses it with
a ValueError naming the file and the domain (as :func:`radiokit.measure.improvement_factor`
does), so no NaN improvement factor is ever written. A change ratio whose background did not
measurably change (:func:`radiokit.measure.change_ratio_se`) is NaN, with the reason beside it.
Each improvement factor and change ratio carries its standard error, estimated from the images
(``improvement_factor_se`` per domain, ``change_ratio_se`` per pair; schema 1.3; 1.4 adds ``pixel_size_recorded``).

``results.json`` is strict JSON (:mod:`radiokit._json`): a number that is not finite (a CNR is
infinite when the background's noise is zero, as in a noiseless simulation) is written ``null``,
and the object's ``"not_finite"`` maps its JSON pointer to ``"Infinity"``, ``"-Infinity"`` or
``"NaN"``; :meth:`Results.from_json` puts the numbers back. Any other ``null`` is "not recorded".
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from radiokit._json import Refused, dumps_readable, loads_checked, restore
from radiokit.checks import is_integer, is_number
from radiokit.enhance import Domain
from radiokit.errors import FormatError

__all__ = [
    "SCHEMA_VERSION",
    "k_label",
    "KMeasure",
    "DomainMeasures",
    "PairResult",
    "PairQuality",
    "Bound",
    "Rois",
    "Results",
    "Enhancement",
    "Images",
    "load_results",
]

#: ``major.minor``: a reader refuses another major version; a minor one only adds keys.
SCHEMA_VERSION = "1.4"
# 1.1: registration/<pair>/rois_ok (do the ROIs lie where the motion was observed?)
# 1.2: strict JSON: non-finite numbers written null and named in "not_finite" (radiokit._json)
# 1.3: standard errors: domains/<d>/improvement_factor_se, change_ratio_se, and change_ratio_reason
#      (why a change ratio is NaN: its background did not measurably change)
# 1.4: pixel_size_recorded (False: the file recorded none, pixel_size_mm was assumed)


def k_label(k) -> str:
    """The text form of an enhancement factor (``1.0 -> "1"``, ``1.5 -> "1.5"``)."""
    return f"{float(k):g}"


def sig3(x: float) -> str:
    """Three significant digits, trailing zeros kept ("10.0" beside "16.6", not "10"; "3.10") and
    no bare point ("126", not "126.")."""
    return f"{float(x):#.3g}".rstrip(".")


def pm(se) -> str:
    """`` ± se`` to two significant digits (a standard error says no more); ``""`` for None (not
    estimated: a results.json before schema 1.3); `` ± 0`` for none at all (noise-free data:
    "0.0" claimed a digit)."""
    if se is None:
        return ""
    s = float(se)
    if not math.isfinite(s):
        return " \u00b1 n/a"  # not estimable ("± nan" read as a number)
    if s == 0:
        return " \u00b1 0"
    return f" \u00b1 {s:.0f}" if s >= 10 else f" \u00b1 {s:#.2g}"  # "12." and "1.5e+02" were #.2g's


def value_pm(value, se, decimals: int = 2) -> str:
    """``value`` with :func:`pm`'s `` ± se``: to ``decimals`` places, or to the place of the standard
    error's second significant digit where that lies further right. Rounded coarser than its
    error a value misstates it (review s42rep: "0.98 ± 0.0040" for 0.9849, off by 1.2 errors).

    >>> value_pm(0.98493, 0.00401), value_pm(0.7671, 0.23, 3), value_pm(1.5, None)
    ('0.9849 \u00b1 0.0040', '0.767 \u00b1 0.23', '1.50')
    >>> value_pm(1.23456789, 1e-12), value_pm(1234.5, 12), value_pm(1.1, float("nan"))
    ('1.234568 \u00b1 1.0e-12', '1234.50 \u00b1 12', '1.10 \u00b1 n/a')
    """
    s = float(se) if se is not None else math.nan
    if math.isfinite(s) and s > 0:
        # at most 6 places: an error of 1e-12 (noise-free data) asked for 13 digits, 1e-300 for 300
        decimals = min(max(decimals, 1 - math.floor(math.log10(s))), max(decimals, _MAX_PLACES))
    return f"{float(value):.{decimals}f}{pm(se)}"


_MAX_PLACES = 6


@dataclass(frozen=True)
class KMeasure:
    """The enhanced image's measurements at one k (``bound``: None where no bound holds)."""

    k: float
    contrast: float
    cnr: float
    weber: float
    improvement_factor: float
    bound: float | None = None
    improvement_factor_se: float | None = None  #: None: not estimated (a results.json before 1.3)


@dataclass(frozen=True)
class DomainMeasures:
    """The reference's contrast, CNR and Weber contrast in one domain, and each k's."""

    domain: Domain
    contrast_reference: float
    cnr_reference: float
    weber_reference: float
    per_k: tuple[KMeasure, ...]

    def at(self, k) -> KMeasure:
        """The measurements at ``k``; KeyError if it was not computed."""
        for m in self.per_k:
            if m.k == float(k):
                return m
        raise KeyError(f"k = {k_label(k)} was not computed (ks: {', '.join(k_label(m.k) for m in self.per_k)})")

    def to_json(self) -> dict:
        by_k = {
            name: {k_label(m.k): getattr(m, name) for m in self.per_k}
            for name in ("contrast", "cnr", "weber", "improvement_factor")
        }
        bounds = {k_label(m.k): m.bound for m in self.per_k}
        ses = {k_label(m.k): m.improvement_factor_se for m in self.per_k}
        return {
            "contrast_reference": self.contrast_reference,
            "cnr_reference": self.cnr_reference,
            "weber_reference": self.weber_reference,
            **by_k,
            "bound": bounds if any(b is not None for b in bounds.values()) else {},
            **({"improvement_factor_se": ses} if any(v is not None for v in ses.values()) else {}),
        }

    @classmethod
    def from_json(cls, domain, d: dict) -> DomainMeasures:
        ses = d.get("improvement_factor_se") or {}
        per_k = tuple(
            KMeasure(
                float(key),
                d["contrast"][key],
                d["cnr"][key],
                d["weber"][key],
                v,
                (d.get("bound") or {}).get(key),
                ses.get(key),
            )
            for key, v in d["improvement_factor"].items()
        )
        return cls(Domain(domain), d["contrast_reference"], d["cnr_reference"], d["weber_reference"], per_k)


class PairQuality(dict):
    """A registered pair's quality as ``results.json`` records it, read-only: the numbers of
    :class:`radiokit.register.Quality`, the pipeline's verdict (``ok`` False, with the ``reason``,
    also where its own checks flagged the pair) and what the run chose (``preset``, ...).

    Each is a typed attribute (``quality.rc_after``), None where the file records none (an older
    radiokit's, or a method that has none); the object is also the dict of the keys recorded, in
    the file's order (``quality["ok"]``, ``dict(quality)``), as it was: a dict, so that code
    written for one still works (``json.dumps(quality)``, ``quality.copy()``, ``quality | {...}``
    raised TypeError when it was a Mapping only: review s43rr); every change to it is refused.
    Only what is recorded is serialised, so a file reads back and writes out byte for byte.
    """

    __slots__ = ()

    # radiokit.register.Quality's fields (a test keeps the two lists together)
    rc_before: float | None
    rc_after: float | None
    ncc_before: float | None
    ncc_after: float | None
    folds: int | None
    min_det_j: float | None
    iterations: int | None
    seconds: float | None
    converged: bool | None
    observed_fraction: float | None
    interior_observed: float | None
    misaligned_fraction: float | None
    excess_kept: float | None
    residual_motion: float | None
    body_scale: float | None
    affine_bound: float | None
    disagreement: float | None
    rim_share: float | None
    inconsistency: float | None
    noise: float | None
    ok: bool | None
    reason: str | None
    note: str | None
    # what the pipeline adds (radiokit.register.Registration.run_record)
    preset: str | None  #: a B-spline method's preset (auto's choice)
    preset_reason: str | None  #: why auto chose it
    initial: str | None  #: what the field started from
    clipped_fixed: int | None  #: extreme pixels clipped before registering
    clipped_moving: int | None
    regularisation_check: str | None  #: the second run's preset (register(..., regularisation_check=True))
    regularisation_check_seconds: float | None

    def __init__(self, items: Mapping | None = None):
        super().__init__(items or {})

    def __getattr__(self, name):
        # only where normal lookup failed: the annotated names are no class attributes
        if name in PairQuality.__annotations__:
            return self.get(name)
        raise AttributeError(f"{type(self).__name__!r} object has no attribute {name!r}")

    def __setattr__(self, name, value):
        raise AttributeError(f"{type(self).__name__} is read-only (a record of the run): cannot set {name!r}")

    def _refuse(self, *args, **kwargs):
        raise TypeError(f"{type(self).__name__} is read-only (a record of the run): change a copy, dict(quality)")

    # dict's every way of changing it in place (a copy, dict(q), q.copy() or q | {...}, is a plain dict)
    __setitem__ = __delitem__ = __ior__ = clear = pop = popitem = setdefault = update = _refuse

    def __dir__(self):
        return sorted(set(super().__dir__()) | set(PairQuality.__annotations__))

    def __reduce__(self):
        # not dict's (it would fill the new object item by item, which is refused)
        return PairQuality, (dict(self),)

    def __repr__(self) -> str:
        return f"PairQuality({dict(self)!r})"


@dataclass(frozen=True)
class PairResult:
    """One registered pair (``moving -> reference`` step numbers): its registration's quality,
    the pipeline's checks of it, and the intensity-change ratio per domain."""

    moving: int
    reference: int
    method: str
    #: the registration's own numbers (:class:`PairQuality`; a dict given is taken as its keys)
    quality: PairQuality
    change_ratio: dict  #: Domain -> ratio
    rois_observed: dict | None = None  #: "inclusion"/"background" -> fraction of the ROI observed
    cross_check: dict | None = None  #: see radiokit.pipeline.cross_check
    epe: dict | None = None  #: simulated files: median/p95 end-point error (px), body and ROIs
    #: both ROIs mostly where the motion was observed (radiokit.pipeline.rois_verdict; False also
    #: makes ``ok`` False, with the reason); None without a confidence map or in a 1.0 file
    rois_ok: bool | None = None
    change_ratio_se: dict | None = None  #: Domain -> standard error (NaN where the ratio is)
    #: Domain -> why the ratio is NaN (the background did not measurably change); absent: measured
    change_ratio_reason: dict | None = None

    def __post_init__(self):
        if not isinstance(self.quality, PairQuality):  # the pipeline and older callers give a dict
            object.__setattr__(self, "quality", PairQuality(self.quality))

    @property
    def name(self) -> str:
        return f"{self.moving}->{self.reference}"

    @property
    def ok(self) -> bool:
        return bool(self.quality.get("ok"))

    @property
    def reason(self) -> str:
        return self.quality.get("reason") or ""

    def registration_json(self) -> dict:
        q = dict(self.quality)
        q["method"] = self.method
        if self.rois_observed is not None:
            q["rois_observed"] = dict(self.rois_observed)
        if self.rois_ok is not None:
            q["rois_ok"] = bool(self.rois_ok)
        if self.cross_check is not None:
            q["cross_check"] = dict(self.cross_check)
        q.update(self.epe or {})
        return q

    @classmethod
    def from_json(
        cls, name: str, registration: dict, change_ratio: dict, se: dict | None = None, reason: dict | None = None
    ) -> PairResult:
        q = dict(registration)
        a, _, b = name.partition("->")
        extras = {key: q.pop(key, None) for key in ("method", "rois_observed", "cross_check", "rois_ok")}
        if extras["rois_ok"] is not None and not isinstance(extras["rois_ok"], bool):
            raise ValueError(f"registration {name!r}: rois_ok is {extras['rois_ok']!r}, not true, false or null")
        epe = {key: q.pop(key) for key in ("epe_median", "epe_p95", "epe_roi_median", "epe_roi_p95") if key in q}
        return cls(
            int(a),
            int(b),
            extras["method"],
            q,
            {Domain(d): v for d, v in change_ratio.items()},
            extras["rois_observed"],
            extras["cross_check"],
            epe or None,
            extras["rois_ok"],
            {Domain(d): v for d, v in se.items()} if se is not None else None,
            {Domain(d): v for d, v in reason.items()} if reason else None,
        )


@dataclass(frozen=True)
class Bound:
    """The improvement factor's bound for the main pair: ``mu_b * delta_gap`` and how it was had."""

    mu_dg: float | None
    basis: str


@dataclass(frozen=True)
class Rois:
    """``crop``: the kept rectangle of the full frame; ``inclusion``/``background``: the ROIs in
    the cropped image. All ``(row0, row1, col0, col1)``, half-open pixels."""

    crop: tuple[int, int, int, int]
    inclusion: tuple[int, int, int, int]
    background: tuple[int, int, int, int]

    def to_json(self) -> dict:
        return {"crop": list(self.crop), "inclusion": list(self.inclusion), "background": list(self.background)}


@dataclass(frozen=True)
class Results:
    """What :func:`radiokit.pipeline.process` measured on one experiment file."""

    source: str
    scene: str | None
    simulated: bool
    pixel_size_mm: float
    domain: Domain  #: the headline domain
    ks: tuple[float, ...]
    method: str
    steps: tuple[int, ...]
    ratios: tuple[float, ...]
    rois: Rois
    domains: dict  #: Domain -> DomainMeasures
    pairs: tuple[PairResult, ...]
    main_pair: str
    profiles_row: int
    bound: Bound
    paper: dict
    timings: dict = field(default_factory=dict)  #: seconds per stage (filled in as the run goes)
    control: Results | None = None
    pixel_size_recorded: bool = True  #: False: the file records none; :attr:`pixel_size_mm` was assumed

    def __post_init__(self):
        # the paper's improvement factors keyed by k as numbers, as improvement_factor's (given
        # as results.json holds them, "1", or as numbers); k_label makes them text again in to_json
        if isinstance(self.paper, dict) and isinstance(self.paper.get("improvement_factor"), dict):
            by_k = {float(k): v for k, v in self.paper["improvement_factor"].items()}
            object.__setattr__(self, "paper", {**self.paper, "improvement_factor": by_k})

    def pair(self, name: str) -> PairResult:
        """The pair ``name`` (``"moving->reference"``, as :attr:`main_pair`); KeyError naming the
        pairs held otherwise (was a bare StopIteration)."""
        for p in self.pairs:
            if p.name == name:
                return p
        held = ", ".join(p.name for p in self.pairs) or "none"
        raise KeyError(f"no pair {name!r} in these results; they hold {held}")

    @property
    def improvement_factor(self) -> dict:
        """The headline domain's improvement factor per k (float keys)."""
        return {m.k: m.improvement_factor for m in self.domains[self.domain].per_k}

    def to_json(self) -> dict:
        """The JSON form of the record, its numbers as numbers (an infinite CNR is ``inf``: the
        Python API's view); :meth:`write_json` writes it strict (a non-finite number null, named in
        ``"not_finite"``: :func:`radiokit._json.strict`)."""
        out = {
            "schema_version": SCHEMA_VERSION,
            "source": self.source,
            "scene": self.scene,
            "simulated": self.simulated,
            "pixel_size_mm": self.pixel_size_mm,
            "pixel_size_recorded": self.pixel_size_recorded,
            "domain": self.domain.value,
            "ks": list(self.ks),
            "method": self.method,
            "steps": list(self.steps),
            "ratios": list(self.ratios),
            "rois": self.rois.to_json(),
            "improvement_factor": {k_label(k): v for k, v in self.improvement_factor.items()},
            "domains": {d.value: m.to_json() for d, m in self.domains.items()},
            "change_ratio": {p.name: {d.value: v for d, v in p.change_ratio.items()} for p in self.pairs},
            "change_ratio_se": {
                p.name: {d.value: v for d, v in p.change_ratio_se.items()}
                for p in self.pairs
                if p.change_ratio_se is not None
            },
            "change_ratio_reason": {
                p.name: {d.value: v for d, v in p.change_ratio_reason.items()}
                for p in self.pairs
                if p.change_ratio_reason
            },
            "registration": {p.name: p.registration_json() for p in self.pairs},
            "main_pair": self.main_pair,
            "profiles_row": self.profiles_row,
            "paper": _paper_json(self.paper),
            "timings": dict(self.timings),
            "bound": {"mu_dg": self.bound.mu_dg, "basis": self.bound.basis},
        }
        if self.control is not None:
            out["control"] = self.control.to_json()
        return out

    @classmethod
    def from_json(cls, d: dict, where="results") -> Results:
        """The records of :meth:`to_json`'s output; FormatError naming ``where`` for another major version."""
        if not isinstance(d, dict):
            raise FormatError(where, f"holds a JSON {type(d).__name__}, not the object of a results.json")
        version = d.get("schema_version", "0")
        if not isinstance(version, str) or version.split(".")[0] != SCHEMA_VERSION.split(".")[0]:
            shown = version if isinstance(version, str) else json.dumps(version)
            raise FormatError(
                where,
                f"results schema version {shown}, this radiokit reads {SCHEMA_VERSION} "
                "(re-run `radiokit process` to rewrite it)",
            )
        try:  # before the fields' checks: they see the numbers as written
            d = restore(d, str(where))
        except ValueError as exc:
            raise FormatError(where, f"results.json {str(exc).removeprefix(f'{where}: ')}") from None
        _check_fields(d, where)
        ses, reasons = d.get("change_ratio_se") or {}, d.get("change_ratio_reason") or {}
        pairs = tuple(
            PairResult.from_json(name, q, d["change_ratio"][name], ses.get(name), reasons.get(name))
            for name, q in d["registration"].items()
        )
        r = d["rois"]
        return cls(
            d["source"],
            d.get("scene"),
            bool(d["simulated"]),
            d["pixel_size_mm"],
            Domain(d["domain"]),
            tuple(d["ks"]),
            d["method"],
            tuple(d["steps"]),
            tuple(d["ratios"]),
            Rois(tuple(r["crop"]), tuple(r["inclusion"]), tuple(r["background"])),
            {Domain(k): DomainMeasures.from_json(k, v) for k, v in d["domains"].items()},
            pairs,
            d["main_pair"],
            d["profiles_row"],
            Bound(d["bound"]["mu_dg"], d["bound"]["basis"]),
            d.get("paper") or {},
            dict(d.get("timings") or {}),
            cls.from_json(d["control"], f"{where} (control)") if d.get("control") else None,
            bool(d.get("pixel_size_recorded", True)),  # (absent from files written before it was)
        )

    def write_json(self, path) -> Path:
        """Write results.json; refused (ValueError naming ``path``) before the file, where
        :func:`load_results` would refuse it back: nested past radiokit's depth (a caller's
        ``paper``) or past :data:`MAX_JSON_BYTES` (s53: written, then refused by its reader).

        Written whole or not at all: a temporary file beside ``path``, renamed over it when
        complete (:func:`radiokit.io.atomic_path`). Why: ``Path.write_text`` truncated the file in
        place, so a crash or a full disk mid-write left a cut results.json where the last good
        one was (review s53rvoff). As a library call an existing ``path`` is replaced; the
        commands refuse one without ``--overwrite`` before they run."""
        from radiokit._names import shown
        from radiokit.io import atomic_path

        path = Path(path)
        text = dumps_readable(self.to_json(), shown(path), "results.json", MAX_JSON_BYTES, indent=1)
        with atomic_path(path, overwrite=True) as tmp:
            tmp.write_text(text)
        return path


def _paper_json(paper):
    """:attr:`Results.paper` as results.json holds it: k keyed by :func:`k_label`."""
    if isinstance(paper, dict) and isinstance(paper.get("improvement_factor"), dict):
        return {**paper, "improvement_factor": {k_label(k): v for k, v in paper["improvement_factor"].items()}}
    return paper


@dataclass(frozen=True)
class Enhancement:
    """The main pair in one domain: reference, registered step, ``D = reference - registered``
    (:func:`radiokit.enhance.difference`) and the enhanced image per k, in the order of the ks."""

    domain: Domain
    reference: np.ndarray
    registered: np.ndarray
    difference: np.ndarray
    images: tuple[tuple[float, np.ndarray], ...]


@dataclass(frozen=True)
class Images:
    """The images of a run (cropped): what ``results.h5`` and the report show."""

    steps: np.ndarray
    reference: np.ndarray
    registered: np.ndarray
    moving: np.ndarray
    displacement: np.ndarray
    det_j: np.ndarray
    confidence: np.ndarray | None
    enhanced: dict  #: Domain -> Enhancement
    profiles: dict
    truth_displacement: np.ndarray | None = None
    epe_map: np.ndarray | None = None

    def as_dict(self, record: Results) -> dict:
        """The arrays keyed by name (the report's and ``Result.arrays``' form)."""
        out = {
            "steps": self.steps,
            "step_numbers": list(record.steps),
            "ratios": list(record.ratios),
            "reference": self.reference,
            "registered": self.registered,
            "moving": self.moving,
            "displacement": self.displacement,
            "det_j": self.det_j,
            "confidence": self.confidence,
            "enhanced": {d.value: {k_label(k): img for k, img in e.images} for d, e in self.enhanced.items()},
            "reference_by_domain": {d.value: e.reference for d, e in self.enhanced.items()},
            "difference": {d.value: e.difference for d, e in self.enhanced.items()},
            "profiles": self.profiles,
        }
        if self.truth_displacement is not None:
            out["truth_displacement"], out["epe_map"] = self.truth_displacement, self.epe_map
        return out


#: a results.json holds numbers for a few steps and ks: kilobytes. A file this size is not one,
#: and is refused before it is read into memory.
MAX_JSON_BYTES = 64 * 2**20


def load_results(path) -> Results:
    """Read a ``results.json`` written by :func:`radiokit.pipeline.process` into :class:`Results`.

    A newer minor schema version (``1.x``) reads: it only adds keys, which are ignored.

    Raises
    ------
    FormatError
        If the file is missing, larger than :data:`MAX_JSON_BYTES`, not UTF-8 JSON (or nested past
        Python's recursion limit), lacks a field or holds one of the wrong type, or has another
        major schema version.
    """
    from radiokit.io._layout import check_regular_file

    path = Path(path)
    check_regular_file(path, "a results.json")
    try:
        size = path.stat().st_size
        if size > MAX_JSON_BYTES:
            raise FormatError(path, f"is {size / 1e9:.1f} GB; a results.json is at most {MAX_JSON_BYTES >> 20} MiB")
        # past radiokit's depth (radiokit._json): one 900 deep loaded, and to_json recursed past
        # Python's limit (s52). from_json puts back the not_finite numbers, naming the file
        data = loads_checked(path.read_bytes().decode("utf-8"), "results.json", MAX_JSON_BYTES)
    except OSError as exc:
        raise FormatError(path, f"cannot be read: {exc.strerror or exc}") from None
    except Refused as exc:
        raise FormatError(path, f"not a results.json: {exc}") from None
    except ValueError as exc:  # JSONDecodeError and UnicodeDecodeError are ValueErrors
        if isinstance(exc, FormatError):
            raise
        raise FormatError(path, f"not a results.json: not UTF-8 JSON ({' '.join(str(exc).split())[:200]})") from None
    try:
        return Results.from_json(data, str(path))
    except (KeyError, TypeError, ValueError, AttributeError, RecursionError) as exc:
        if isinstance(exc, FormatError):
            raise
        raise FormatError(path, f"not a radiokit results.json: {type(exc).__name__} {exc}") from None


def _maybe_number(v) -> bool:  # numpy scalars too: process_many hands over to_json()'s dict unserialised
    return v is None or is_number(v)


def _list_of(check, n=None):
    return lambda v: isinstance(v, list) and (n is None or len(v) == n) and all(map(check, v))


def _dict_of(check):
    return lambda v: isinstance(v, dict) and all(map(check, v.values()))


def _k_keyed(v) -> bool:
    """``{k label: number or None}``, every key a number (k_label's text)."""
    if not _dict_of(_maybe_number)(v):
        return False
    try:
        return all(math.isfinite(float(k)) for k in v)
    except ValueError:
        return False


_BOX = _list_of(is_integer, 4)
_DOMAIN_FIELDS = {
    "contrast_reference": _maybe_number,
    "cnr_reference": _maybe_number,
    "weber_reference": _maybe_number,
    "contrast": _k_keyed,
    "cnr": _k_keyed,
    "weber": _k_keyed,
    "improvement_factor": _k_keyed,
    "improvement_factor_se": lambda v: v is None or _k_keyed(v),  # 1.3 on
}
#: what :meth:`Results.from_json` reads, and what each must be (None: optional)
_FIELDS = {
    "source": (str,),
    "scene": (str, None),
    "simulated": (bool, np.bool_),
    "pixel_size_mm": is_number,
    "pixel_size_recorded": (bool, np.bool_, None),
    "domain": (str,),
    "ks": _list_of(is_number),
    "method": (str,),
    "steps": _list_of(is_integer),
    "ratios": _list_of(_maybe_number),
    "rois": lambda v: isinstance(v, dict) and all(_BOX(v.get(k)) for k in ("crop", "inclusion", "background")),
    "domains": _dict_of(lambda m: isinstance(m, dict) and all(c(m.get(k)) for k, c in _DOMAIN_FIELDS.items())),
    "change_ratio": _dict_of(_dict_of(_maybe_number)),
    "registration": _dict_of(lambda q: isinstance(q, dict)),
    "main_pair": (str,),
    "profiles_row": is_integer,
    "paper": (dict, None),
    "timings": (dict, None),
    "bound": lambda v: isinstance(v, dict) and _maybe_number(v.get("mu_dg")) and isinstance(v.get("basis"), str),
    "control": (dict, None),
}

#: what a 1.3 file adds (absent from older ones)
_OPTIONAL = {
    "change_ratio_se": _dict_of(_dict_of(_maybe_number)),
    "change_ratio_reason": _dict_of(_dict_of(lambda v: isinstance(v, str))),
}


def _check_fields(d: dict, where) -> None:
    """Refuse, naming the key, a field :meth:`Results.from_json` would misread (a string where a
    list of numbers belongs iterates into characters; a missing one is a KeyError)."""
    for key, check in _FIELDS.items():
        value = d.get(key)
        if isinstance(check, tuple):
            ok = (None in check and value is None) or isinstance(value, tuple(t for t in check if t is not None))
        else:
            ok = check(value)
        if not ok:
            got = "missing" if key not in d else f"{type(value).__name__} {json.dumps(value)[:60]}"
            raise FormatError(where, f"results.json field {key!r} is {got}: not what radiokit writes there")
    for key, check in _OPTIONAL.items():
        if key in d and not check(d[key]):
            raise FormatError(
                where, f"results.json field {key!r} is {json.dumps(d[key])[:60]}: not what radiokit writes there"
            )
    for name in d["registration"]:
        a, arrow, b = name.partition("->")
        if not (arrow and a.isdigit() and b.isdigit()) or name not in d["change_ratio"]:
            raise FormatError(
                where,
                f"results.json registration {name!r}: expected a 'moving->fixed' pair of steps with a change_ratio",
            )
    if d["main_pair"] not in d["registration"]:
        raise FormatError(where, f"results.json main_pair {d['main_pair']!r} is none of the registered pairs")
