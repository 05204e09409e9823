"""The ``radiokit`` command: thin subcommands over the library.

Subcommands of other packages (``sim``, ``acquisition``) register themselves through the
``radiokit.commands`` entry-point group, so this module imports neither.
"""

from __future__ import annotations

import argparse
import codecs
import contextlib
import io
import json
import logging
import math
import os
import signal
import sys
import warnings
from pathlib import Path

try:  # the second the imports take: Ctrl-C there printed an import's traceback (review s38b)
    from importlib.metadata import entry_points  # 0.18 s of them (email, socket, ...)

    import numpy as np

    from radiokit import __version__
    from radiokit._names import controls_escaped, shown
    from radiokit.errors import RadiokitError
except KeyboardInterrupt:
    print("radiokit: interrupted while starting: nothing was read, sent or written", file=sys.stderr)
    raise SystemExit(130) from None

#: radiokit.register's B-spline presets and rc's automatic choice between them; a literal so that
#: --help does not import scipy (tests/test_cli.py checks it against the registry)
PRESET_NAMES = ("default", "fast", "weak", "weak-fast", "silent", "silent-fast", "auto", "auto-fast")

__all__ = ["main", "build_parser"]


def _inputs(args, paths) -> list:
    """``paths`` given. The files their HDF5 frames are read from (external links, virtual
    sources, external raw storage) are inputs too: :func:`radiokit.io.check_output` refuses an
    output onto one of them itself, for the library's callers as for these commands."""
    return [p for p in paths if p]


def _raw_hints(args) -> dict:
    hints = {}
    for name in ("preset", "dtype", "byteorder", "offset", "format"):  # a dataset: _dataset_hints
        value = getattr(args, name, None)
        if value is not None:
            hints[name] = value
    if getattr(args, "shape", None):
        hints["shape"] = tuple(args.shape)
    if getattr(args, "allow_external", False):
        hints["allow_external"] = True
    if getattr(args, "narrow_frames", False):
        hints["narrow_frames"] = True
    return hints


#: --narrow-frames: a stack whose last axis is far the shortest is refused as stored rows x cols x n
_NARROW_HELP = (
    "read an HDF5 stack (n, rows, cols) whose cols are far fewer than its n and rows as it is stored (refused "
    "otherwise: such a stack is mostly rows x cols x n, numpy's dstack)"
)


#: the rule of every option naming a dataset, as the commands' help says it
_DATASET_RULE = (
    "A dataset option applies to the HDF5 files among the files it covers; the others (TIFF, raw, ITEX) are "
    "read as they are, and it is refused where none of them is HDF5."
)


def _dataset_hints(args, kinds: dict) -> dict:
    """The reader's dataset hints for each kind of file a command reads (``kinds``: kind -> its
    files, e.g. ``{"dark": [...], "flat": [...]}``): the kind's own option (``--dark-dataset``,
    ``--fixed-dataset``) over ``--dataset``, which covers the kinds without one.

    One rule for every such option and command: the dataset applies to the HDF5 files among
    those the option covers (the reader's ``hdf5_dataset``), their TIFF, raw and ITEX files read
    as they are; refused, naming the option and a file, where none of them is HDF5 (an option
    that applies to nothing given is a slip to say, not to drop). Why: ``info`` and ``correct``
    applied ``--dataset`` so (s50) while ``calibrate`` and ``register`` refused a TIFF beside it,
    and each of their per-kind options did too (s51)."""
    own = {kind: getattr(args, f"{kind}_dataset", None) for kind in kinds}
    shared = [p for kind, paths in kinds.items() if not own[kind] for p in paths]
    fmt = getattr(args, "format", None)  # --format: every file read as that
    if getattr(args, "dataset", None) and kinds and not shared:  # dropped in silence before (review s51rv2)
        raise ValueError(
            f"--dataset {args.dataset} applies to no file: {' and '.join(f'--{k}-dataset' for k in kinds)} "
            "name every file's dataset; give one or the other"
        )
    both = _over_hdf5_files("--dataset", getattr(args, "dataset", None), shared, fmt)
    return {
        kind: _over_hdf5_files(f"--{kind}-dataset", own[kind], paths, fmt) if own[kind] else both
        for kind, paths in kinds.items()
    }


def _over_hdf5_files(option: str, dataset, paths, fmt=None) -> dict:
    """``dataset`` (given by ``option``) for the HDF5 files among ``paths``, by the rule of
    :func:`_dataset_hints`: ``{"hdf5_dataset": dataset}``, or ``{}`` where none is given."""
    from radiokit.io import FormatError, sniff

    if not dataset or not paths:
        return {}
    found = []
    for path in paths:
        try:
            found.append((path, fmt or sniff(path)))
        except (OSError, FormatError):  # a missing or unreadable file is named by its reader
            return {"hdf5_dataset": dataset}
    if not any(f == "hdf5" for _, f in found):
        path, f = found[0]
        what = {
            "tiff": "a TIFF",
            "itex": "an ITEX .img",
            "raw": "headerless raw",
            "png": "a PNG",
            "jpeg": "a JPEG",
            "jpeg2000": "a JPEG 2000 file",
            "dicom": "a DICOM file",
        }.get(f, f)
        # under --format the file's own kind is not what refused it (an HDF5 file was called "a TIFF")
        what = f"read as {fmt} (--format {fmt})" if fmt else what
        others = ", nor is any other file it applies to" if len(found) > 1 else ""
        raise FormatError(path, f"{option} names a dataset of HDF5 files, and this file is {what}, not HDF5{others}")
    return {"hdf5_dataset": dataset}


def _add_raw_hints(p):
    # --format with the command's own options: it says how every file is read (a DICOM, a PNG),
    # and was listed under the raw group, where a reader of anything but raw files never looked
    p.add_argument(
        "--format",
        choices=["raw", "tiff", "itex", "hdf5", "png", "jpeg", "jpeg2000", "dicom"],
        help="read the files as this format, skipping detection (default: detected from each file's contents)",
    )
    g = p.add_argument_group("raw files (headerless)")
    g.add_argument(
        "--preset", help="geometry preset, e.g. c7942, c7942-2x2 (default: from the size where only one fits)"
    )
    # exactly two numbers: nargs="+" took the file after them for a third ("invalid int value: 'f.raw'");
    # the frame count follows from the file's size
    g.add_argument("--shape", type=int, nargs=2, metavar=("ROWS", "COLS"), help="frame size, e.g. --shape 2240 2240")
    g.add_argument("--dtype", help="pixel type with --shape, e.g. '<f4' for float32 (default '<u2', 16-bit)")
    g.add_argument("--byteorder", choices=["<", ">", "little", "big"], help="byte order (default little)")
    g.add_argument("--offset", type=int, help="bytes to skip at the start")
    g = p.add_argument_group("HDF5 files of other layouts", _DATASET_RULE)
    g.add_argument("--dataset", help="the dataset holding the frames (rows, cols) or (n, rows, cols), e.g. scan/data")
    g.add_argument(
        "--allow-external",
        action="store_true",
        help="read data in other files: HDF5 external links, external raw storage and virtual datasets, "
        "and the planes a multi-file OME-TIFF keeps in the files beside it",
    )
    g.add_argument("--narrow-frames", action="store_true", help=_NARROW_HELP)


# -- info --------------------------------------------------------------------------------------
def _gdal_scaling(g: dict | None) -> str | None:
    """A GDAL-scaled TIFF's scaling in words. Why: its range is of values, not of the stored
    counts, and nothing said so (review s46rio)."""
    if not g:
        return None
    nodata = f", NODATA {g['nodata']:g} as NaN" if "nodata" in g else ""
    return f"stored * {g['scale']:g} + {g['offset']:g}{nodata}"


def _clinical_summary(meta: dict) -> dict:
    """A DICOM's or PNG's items of note: what its values are (the Modality LUT applied,
    MONOCHROME1 read as stored) and where its pitch came from."""
    if meta.get("format") == "png":
        return {"png_bit_depth": meta.get("png_bit_depth")}
    if meta.get("format") in ("jpeg", "jpeg2000"):
        return {"compression": meta.get("compression")}
    r = meta.get("dicom_rescale")
    return {
        "modality": meta.get("modality") or None,
        "transfer_syntax": meta.get("transfer_syntax"),
        "lossy": meta.get("lossy"),
        "photometric": meta.get("photometric_note") or meta.get("photometric"),
        "rescale": f"stored * {r['slope']:g} + {r['intercept']:g} (RescaleSlope/Intercept)" if r else None,
        "pixel_size_from": meta.get("pixel_size_source")
        + (f" (in its {meta['pixel_size_where']})" if meta.get("pixel_size_where") else "")
        if meta.get("pixel_size_source")
        else None,
        "padding": meta.get("pixel_padding"),
    }


def _experiment_summary(meta: dict) -> dict:
    """An experiment file's frames by kind, its steps, its source, and its detector and pitch as
    recorded (where the pitch is not, what the readers assume)."""
    keys = np.asarray(meta.get("image_key", []))
    steps = np.asarray(meta.get("step", np.full(keys.shape, -1)))  # optional in the file
    steps = steps if steps.shape == keys.shape else np.full(keys.shape, -1)
    out = {
        "projections": int(np.sum(keys == 0)),
        "flats": int(np.sum(keys == 1)),
        "darks": int(np.sum(keys == 2)),
        "invalid": int(np.sum(keys == 3)),
        "steps": sorted(int(s) for s in set(steps[(keys == 0) & (steps >= 0)].tolist())),
        "simulated": bool(meta.get("simulated", False)),
    }
    src = meta.get("source", {})
    out["source"] = " ".join(
        f"{src[k]:g} {unit}" if isinstance(src.get(k), (int, float, np.number)) else str(src.get(k))
        for k, unit in (("name", ""), ("voltage", "kV"), ("current", "uA"))
        if k in src and not (isinstance(src[k], (float, np.floating)) and np.isnan(src[k]))
    ).strip()
    out["detector"] = meta.get("detector")
    out["pixel_size_from"] = meta.get("pixel_size_from")
    if meta.get("x_pixel_size") is None and not meta.get("pixel_size_unusable"):
        # the pipeline assumes this pitch and warns; info says it before a run rests on it
        from radiokit.io import C7942_PIXEL_SIZE_MM

        out["pixel_size"] = f"not recorded (readers assume {C7942_PIXEL_SIZE_MM * 1e3:g} \u00b5m, the C7942's)"
    return out


def _summary(meta: dict) -> dict:
    """The few metadata items a person wants to see first."""
    fmt = meta.get("format")
    out = {}
    if fmt == "raw":
        out = {k: meta[k] for k in ("preset", "offset", "pixel_size_mm") if meta.get(k) is not None}
    elif fmt == "itex":
        c = meta.get("comment", {})
        app, cam, acq = c.get("Application", {}), c.get("Camera", {}), c.get("Acquisition", {})
        out = {
            "software": f"{app.get('Software', '?')} {app.get('SoftwareVersion', '')}".strip(),
            "date": f"{app.get('Date', '')} {app.get('Time', '')}".strip(),
            "camera": cam.get("CameraName"),
            "exposure": acq.get("ExposureTime"),
            "file_type": meta.get("file_type"),
            # a sub-array's place on the sensor: else it reads as a whole (binned) frame
            "offset": f"x {meta.get('x_offset', 0)}, y {meta.get('y_offset', 0)}"
            if meta.get("x_offset") or meta.get("y_offset")
            else None,
            "scaling": {
                k: (f"{len(v['values'])} values [{v.get('unit', '')}]" if "values" in v else v.get("name"))
                for k, v in meta.get("scaling", {}).items()
            },
        }
    elif fmt == "experiment":
        out = _experiment_summary(meta)
    elif fmt == "tiff":
        out = {k: v for k, v in meta.get("tags", {}).items() if k in ("Software", "DateTime", "Compression")}
        if meta.get("stacked"):  # frame k of a (2, 5, rows, cols) series is (k // 5, k % 5)
            st = meta["stacked"]
            # (in that order, not the file's: an OME or Micro-Manager file's planes are put in it)
            out["stacked"] = f"{' x '.join(map(str, st['shape']))} ({st['axes']}), read flat in that order"
        if meta.get("bit_depth_from"):  # where a 16-bit file's saturation line comes from
            out["bit_depth"] = f"{meta['bit_depth']} ({meta['bit_depth_from']})"
        out["gdal_scaling"] = _gdal_scaling(meta.get("gdal_scaling"))
    elif fmt in ("dicom", "png", "jpeg", "jpeg2000"):
        out = _clinical_summary(meta)
    elif fmt == "calibration":
        out = _calibration_summary(meta)
    elif fmt == "dxchange":  # its three datasets, keyed as an experiment file's frames
        keys = np.asarray(meta.get("image_key", []))
        out = {kind: int(np.sum(keys == k)) for kind, k in (("projections", 0), ("flats", 1), ("darks", 2))}
    # the pitch wherever the file states it (an experiment's, ImageJ's, OME's, an NXdetector's):
    # register holds two images to it, so the user sees what it will be held to
    if out.get("pixel_size_mm") is None and meta.get("x_pixel_size") is not None:
        # 6 digits: 50 um in metres times 1e3 is 0.049999999999999996 mm, a float32 0.05 mm 0.0500000007
        x, y = (float(f"{v * 1e3:.6g}") for v in (meta["x_pixel_size"], meta.get("y_pixel_size", meta["x_pixel_size"])))
        # a number, as a raw preset's is (JSON readers get one type); (x, y) where they differ
        out["pixel_size_mm"] = x if math.isclose(x, y, rel_tol=1e-6) else [x, y]
    elif out.get("pixel_size_mm") is None and meta.get("pixel_size_unusable"):  # read and ignored: why
        out["pixel_size"] = f"unusable, {meta['pixel_size_unusable']}"
    if "pixel_size_from" in out:  # said after the pitch it is of
        out["pixel_size_from"] = out.pop("pixel_size_from")
    return {k: v for k, v in out.items() if v not in (None, "", {})}


def _calibration_summary(meta: dict) -> dict:
    """A calibration file's lines it fills, named as calibrate named them, and the files and
    datasets its darks and flats were read from (``made from``, one a line)."""
    from radiokit.calibrate import input_lines, line_summary

    prov = meta.get("provenance", {})
    out = line_summary(meta.get("defect_rows", []), meta.get("defect_columns", []), prov)
    unreadable = meta.get("provenance_unreadable")  # (its frames read: info describes the file)
    out |= {"made from": [f"unreadable: {unreadable}"] if unreadable else input_lines(prov)}
    inputs = prov.get("inputs") if not unreadable else None
    if isinstance(inputs, list) and all(isinstance(i, dict) for i in inputs):
        # for --json: the records as written, their names exact (the lines quote them for a
        # terminal, and a JSON reader could not get 'a\nb.tif' back from them); not printed
        out["inputs"] = inputs
    return out


#: The most frames ``info`` holds to judge a file's saturation level by (evenly spaced; its default sample)
_SATURATION_FRAMES = 8


def _saturation_basis(bits, signed, declared, scaling, top, values, itemsize) -> str | None:
    """What ``info`` says its saturation level is taken from. Where the file declares no depth
    (wider than 8 bits) the level is said to be a guess, and one its values (up to half of it)
    say little of. Why (s54): a 14-bit panel's dark said ">= 4095 (from the values)", read as
    the ADC's top, where a dark's values say nothing of it."""
    basis = (
        f"declared {bits}-bit{' signed' if signed else ''}"
        if declared
        else f"from the values, above the declared {bits}-bit range"
        if bits is not None
        else "the 8-bit type's top"
        if itemsize == 1
        else "from the values"
    )
    if scaling:  # (a negative scale's top is the values' floor: not judged, said so)
        basis = f"{basis} of the stored counts, {scaling['text']}" if top is not None else None
    if basis is not None and bits is None and itemsize > 1 and top is not None:
        basis += "; a guess: the file declares no bit depth"
        high = float(np.max(values)) if values.size else None
        if high is not None and high < (float(top) + 1) / 2:
            basis += f", its values (up to {high:.7g}) under half of it: the ADC's may be higher"
    return basis


def _describe(path, src, every: bool, sample: int) -> dict:
    """What ``radiokit info`` reports of one open file: the range of its finite pixels (JSON has
    no NaN or Infinity), the NaN or inf ones and the saturated ones counted, in a few evenly
    spaced frames (``every``: all of them)."""
    from radiokit.calibrate import declared_levels, saturation_level, value_scaling

    lo, hi, saturated, nonfinite, nonfinite_frames = None, None, 0, 0, 0
    n_read = len(src) if every else min(len(src), sample)
    # --all: a range, not an array of every index (a small file may declare 10**8 frames)
    picks = range(len(src)) if every else _spaced(len(src), n_read)
    # the level by the rule calibrate applies (saturation_level), judged on up to 8 evenly spaced
    # frames: its own guess (or the declared 4095 over MSB-aligned counts) called every pixel of a
    # 12-bit TIFF in the high bits saturated, and 8-bit files' 255s went uncounted. Floats are no
    # ADC's words: a level only where the file declares a depth.
    held, top, low, basis = {}, None, None, None
    bits = src.meta.get("bit_depth")
    signed = src.meta.get("bit_depth_signed") is True  # a DICOM's PixelRepresentation 1: it clips at both ends
    # scaled values (GDAL, CF): the level is of the stored counts, given as a value (review s46rio)
    scaling = value_scaling(src.meta)
    if len(src) and (src.dtype.kind in "ui" or bits is not None or scaling):
        held = {int(i): src[int(i)] for i in _spaced(len(src), min(len(src), sample, _SATURATION_FRAMES))}
        parts = [f[np.isfinite(f)] if f.dtype.kind == "f" else f.ravel() for f in held.values()]
        stack = parts[0] if len(parts) == 1 else np.concatenate(parts)  # one frame: no copy of it
        top = saturation_level(stack, bit_depth=bits, scaling=scaling, signed=signed) if stack.size else None
        # the declared ends as the values read them (a scaled file's too): a signed ADC clips at both
        ends = declared_levels(bits, signed, scaling, stack.dtype) if bits is not None else (None, None)
        declared = ends[1] is not None and top == ends[1]
        low = ends[0] if declared and signed else None
        basis = _saturation_basis(bits, signed, declared, scaling, top, stack, src.dtype.itemsize)
        if basis and (word := src.meta.get("bit_depth_word")):  # a DICOM's BitsStored of its whole word
            basis = basis.replace("the file declares no bit depth", f"the file declares only its word ({word})")
    if scaling and top is None:
        basis = f"not checked: values scaled ({scaling['text']})"
    for i in picks:
        frame = held.pop(int(i)) if int(i) in held else src[i]
        if frame.dtype.kind == "f":
            finite = np.isfinite(frame)
            bad = int(frame.size - np.count_nonzero(finite))
            nonfinite, nonfinite_frames = nonfinite + bad, nonfinite_frames + (bad > 0)
            frame = frame[finite]
        if frame.size:
            fmin, fmax = frame.min(), frame.max()
            lo = fmin if lo is None else min(lo, fmin)
            hi = fmax if hi is None else max(hi, fmax)
        if top is not None:
            saturated += int(np.count_nonzero(frame >= top))
        if low is not None:  # a signed ADC's bottom (-2048 of 12 bits) is a clip too
            saturated += int(np.count_nonzero(frame <= low))
    return {
        "file": str(path),
        "format": src.meta.get("format", src.format),
        "frames": len(src),
        "shape": list(src.frame_shape),
        "dtype": str(src.dtype),
        "range": [lo.item(), hi.item()] if lo is not None else None,
        "frames_read": len(picks),
        # a scaled file whose top is not known: "unknown", never a silent 0 or nothing
        "saturated": saturated if top is not None else "unknown" if scaling else None,
        "saturation": top,
        **({"saturation_low": low} if low is not None else {}),
        "saturation_from": basis if top is not None or scaling else None,
        "nonfinite": nonfinite,
        "nonfinite_frames": nonfinite_frames,
        "metadata": _summary(src.meta) | _stack_domain(src) | _assumed_pitch(src),
    }


def _spaced(n: int, k: int) -> np.ndarray:
    """``k`` evenly spaced indices of ``n`` frames, first and last included."""
    return np.unique(np.linspace(0, n - 1, k).round().astype(int)) if k else np.zeros(0, int)


#: What a corrected stack's pixels are (radiokit.correct's domains): the numbers alone do not say.
_DOMAINS = {
    "log": "log: line integrals -ln(I/I0)",
    "linear": "linear: transmission I/I0",
    "counts": "counts: gain-corrected grey levels",
}


def _stack_domain(src) -> dict:
    """``{"domain": words}`` for a stack ``radiokit correct`` wrote (it records its domain in the
    TIFF's description, or its HDF5 frames' group), else nothing."""
    meta, value = src.meta, None
    if meta.get("format") == "tiff" and isinstance(meta.get("description"), dict):
        value = meta["description"].get("domain")
    elif meta.get("format") == "hdf5":
        from radiokit.io._write import STACK, STACK_FRAMES

        if meta.get("dataset") == f"/{STACK_FRAMES}":
            value = src.hdf5_attribute(STACK, "domain")
    value = value.decode(errors="replace") if isinstance(value, bytes) else value
    return {"domain": _DOMAINS.get(value, value)} if isinstance(value, str) and value else {}


def _assumed_pitch(src) -> dict:
    """``{"pixel_size": "not recorded (assumed N µm)"}`` for a results.h5 whose run assumed its
    pitch: the file leaves NeXus's x_pixel_size out then (it would state the pitch as the data's),
    and its embedded results.json says ``pixel_size_recorded: false``; else nothing."""
    from radiokit.io._results import ENTRY, RESULTS_STEPS

    meta = src.meta
    if meta.get("format") != "hdf5" or meta.get("dataset", "").rsplit("/", 1)[0] != f"/{RESULTS_STEPS}":
        return {}
    if meta.get("pixel_size_mm") is not None:
        return {}
    from radiokit._json import loads_record
    from radiokit.results import MAX_JSON_BYTES

    text = src.hdf5_attribute(ENTRY, "results_json")
    try:
        # past radiokit's depth (radiokit._json), or a pitch past float's range (10**400: s52);
        # results.json's text, read at its bound: 4 MiB, a description's, skipped a long run's (s53)
        numbers = loads_record(text.decode() if isinstance(text, bytes) else text, "results_json", MAX_JSON_BYTES)
        pitch = float(numbers["pixel_size_mm"]) * 1e3
    except (TypeError, ValueError, KeyError, AttributeError, OverflowError):  # not radiokit's JSON: say nothing
        return {}
    if numbers.get("pixel_size_recorded") is not False or not math.isfinite(pitch):
        return {}
    return {"pixel_size": f"not recorded (assumed {pitch:.6g} \u00b5m)"}


def _escaped(value) -> str:
    """``value`` as text, its control characters escaped as Python writes them (``\\x00``, ``\\x1b``):
    a header comment's NUL or escape sequence reached the terminal raw (``ESC [31m`` turned the
    rest of the output red). A text value holding one, or a backslash, is quoted too, its
    backslashes and quotes escaped, as :func:`radiokit._names.shown` prints a name: a TIFF's
    Software tag ``HPD\\\\nTA`` printed as one holding a newline did (s53). Other values (a dict,
    a list) print their texts' ``repr``, escaped already."""
    text = str(value)
    if isinstance(value, str) and ("\\" in text or not text.isprintable()):
        escaped = (
            "\\\\"
            if c == "\\"
            else "\\'"
            if c == "'"
            else c
            if c.isprintable()
            else c.encode("unicode_escape").decode("ascii")
            for c in text
        )
        return "'" + "".join(escaped) + "'"
    return "".join(c if c.isprintable() else c.encode("unicode_escape").decode("ascii") for c in text)


def cmd_info(args) -> int:
    from radiokit.io import open_frames

    if args.all and args.sample is not None:  # --all read every frame and dropped --sample in silence
        raise ValueError(f"--all --sample {args.sample}: give one: every frame, or N of them")
    sample = 8 if args.sample is None else args.sample
    if sample < 1:
        raise ValueError(f"--sample {sample}: expected at least one frame")
    reports, failed = [], 0
    # one bad file among several: its one line on stderr, the others still described (the first
    # error used to end the command with nothing printed for the good files), exit status 2; the
    # JSON has an entry per file given, a bad one's {"file", "error"}, so that its reader sees it too
    hints = _raw_hints(args) | _dataset_hints(args, {"files": args.files})["files"]
    for path in args.files:
        try:
            with open_frames(path, **hints) as src:
                reports.append(_describe(path, src, args.all, sample))
        except Exception as exc:
            if not _user_error(exc) or _interrupted(exc) or _debug(args) or (len(args.files) == 1 and not args.json):
                raise
            failed += 1
            line = _error_line("info", exc, _given_names(args))
            print(line, file=sys.stderr)
            reports.append({"file": str(path), "error": line.removeprefix("radiokit info: ")})
            continue
        if not reports[-1]["frames"]:  # a stack of none: every other command refuses it so
            failed += 1
            reports[-1]["error"] = f"{shown(path)}: no frames"
            print(f"radiokit info: {shown(path)}: no frames", file=sys.stderr)
    status = 2 if failed else 0
    if args.json:  # strict JSON: a NaN or inf in the metadata is null, named in each report's "not_finite"
        from radiokit._json import strict

        print(json.dumps([strict(r) for r in reports], indent=2, default=str, allow_nan=False))
        return status
    # one table over all the files: each item's value in one column, past the longest name (a
    # DICOM's transfer_syntax pushed its value out of the 10 characters the others kept)
    tables = [(rep["file"], _info_rows(rep)) for rep in reports if "frames" in rep]  # (a bad file: on stderr)
    width = max([10, *(len(key) for _, rows in tables for key, _ in rows)])
    for name, rows in tables:
        print(shown(name))
        for key, value in rows:
            print(f"  {key:<{width}} {value}")
    return status


def _info_rows(rep: dict) -> list[tuple[str, str]]:
    """``info``'s items of one file's report ``rep``, as (name, text) rows: the name empty on an
    item's further lines (a calibration's input files)."""
    rows = [("format", str(rep["format"]))]
    none = "" if rep["frames"] else " (no frames)"
    rows.append(("frames", f"{rep['frames']} x {rep['shape'][0]} rows x {rep['shape'][1]} cols, {rep['dtype']}{none}"))
    of = "" if rep["frames_read"] == rep["frames"] else f" (in {rep['frames_read']} of {rep['frames']} frames)"
    if rep["range"] is not None:
        # float32 carries about 7 significant digits; float64's repr printed nine more of noise
        lo, hi = (f"{v:.7g}" if isinstance(v, float) else v for v in rep["range"])
        rows.append(("range", f"{lo} .. {hi}{of}"))
    if rep["saturated"] == "unknown":
        rows.append(("saturated", str(rep["saturation_from"])))
    elif rep["saturated"] is not None:
        # a scaled file's levels are float values (float32: 7 digits)
        level, low = (f"{v:.7g}" if isinstance(v, float) else v for v in (rep["saturation"], rep.get("saturation_low")))
        low = "" if low is None else f" or <= {low}"  # a signed ADC's bottom
        rows.append(("saturated", f"{rep['saturated']} pixel(s) >= {level}{low} ({rep['saturation_from']}){of}"))
    if rep["nonfinite"]:
        k, read_ = rep["nonfinite_frames"], rep["frames_read"]
        plural = "s" if read_ > 1 else ""  # (one frame of one: "1 of 1 frames" read wrong)
        held = f"{k} of the {read_} frames read (of {rep['frames']})" if of else f"{k} of {read_} frame{plural}"
        rows.append(("nonfinite", f"{rep['nonfinite']} pixel(s) NaN or inf in {held}"))
    for key, value in rep["metadata"].items():
        if key == "inputs":  # a calibration's input records, for --json: "made from" says them
            continue
        if key == "made from":  # a calibration's input files, one a line
            rows += _lines_rows(key, value)
        else:
            rows.append((key, _escaped(value)))
    return rows


#: the most lines ``info`` prints of one item (a calibration's input files) before saying how many more
_MOST_LINES = 10


def _lines_rows(key: str, lines: list) -> list[tuple[str, str]]:
    """``info``'s item ``key`` of several ``lines``, one a row, its name on the first: a calibration
    made from 300 single-frame TIFFs names the first few and how many more (``--json`` has them all)."""
    # (as radiokit.calibrate.input_lines wrote them: their names as names print, no _escaped, which
    # printed a name's byte that is not UTF-8 as \udce9)
    first = lines if len(lines) <= _MOST_LINES else lines[: _MOST_LINES - 1]
    rows = [(key if k == 0 else "", line) for k, line in enumerate(first)]
    if len(first) < len(lines):
        rows.append(("", f"... and {len(lines) - len(first)} more (radiokit info --json lists them all)"))
    return rows


# -- calibrate ---------------------------------------------------------------------------------
def _parse_thresholds(items) -> dict:
    from dataclasses import fields

    from radiokit.calibrate import Thresholds

    known = [f.name for f in fields(Thresholds)]
    whole = {f.name for f in fields(Thresholds) if f.type == "int"}  # saturation, smooth_block
    out = {}
    for item in items or ():
        key, sep, value = item.partition("=")
        if not sep:
            raise ValueError(f"--threshold {item!r}: expected NAME=VALUE")
        if key.strip() not in known:
            raise ValueError(f"--threshold {item!r}: unknown name {key.strip()!r}; known: {', '.join(known)}")
        try:
            number = int(value) if key.strip() in whole else float(value)
        except ValueError:
            kind = "a whole number" if key.strip() in whole else "a number"
            raise ValueError(f"--threshold {item!r}: {value!r} is not {kind}") from None
        if not np.isfinite(number):
            raise ValueError(f"--threshold {item!r}: a threshold must be a finite number")
        out[key.strip()] = number
    # checked together, before any frame is read: one at a time against the defaults refused
    # dead_below=0.02 under_below=0.05 (dead_below 0.1 > under_below 0.05), a valid pair
    try:
        Thresholds(**out)
    except ValueError as exc:
        raise ValueError(f"--threshold {' '.join(items or ())}: {exc}") from None
    return out


def _progress(args) -> bool:
    """Progress bars on stderr: not with ``-q``, nor when stderr is not a terminal (a log file or
    a pipe would get every redraw, and a caller reading stderr for the one-line error a bar)."""
    return not getattr(args, "quiet", False) and sys.stderr.isatty()


def _judge_files(darks, flats, dark_hints, flat_hints) -> None:
    """Open every dark and flat file and judge it from its header (frames in it, one frame shape
    per list), before any frame is read: every bad file named, each on its own line
    (:func:`radiokit.io.judge_all`), each closed before the next opens. :func:`_stack` reads them
    afterwards, one at a time."""
    from radiokit.io import FormatError, InputErrors, judge_all

    errors = []
    for paths, hints in ((darks, dark_hints), (flats, flat_hints)):
        shapes = []

        def judge(src, shapes=shapes):
            if not len(src):  # as `radiokit info` says it
                raise FormatError(src.path, "no frames")
            shapes.append((src.path, src.frame_shape))

        found = []
        try:  # one file open at a time: 300 darks held open passed macOS's 256 files
            judge_all(paths, check=judge, **hints)
        except (FormatError, ValueError, OSError) as exc:
            found = list(getattr(exc, "errors", [exc]))
        found = _in_given_order(found + _odd_shapes(shapes), paths)
        # one file of darks and flats both (an experiment-style file) is named once
        errors += [e for e in found if str(e) not in map(str, errors)]
    if errors:
        raise errors[0] if len(errors) == 1 else InputErrors(errors)


def _odd_shapes(shapes) -> list:
    """A FormatError for each file (of ``(path, frame shape)``) whose frames are not the shape most
    of them share (the first file's, where as many share another): np.stack would say only "must
    have the same shape". Why not the first file's: an odd first file named every other one as
    bad, and never itself."""
    from collections import Counter

    from radiokit.io import FormatError

    if not shapes:
        return []
    counts = Counter(shape for _, shape in shapes)
    panel = counts.most_common(1)[0][0]  # ties: the first seen
    first = next(path for path, shape in shapes if shape == panel)
    others = f" and {counts[panel] - 1} other file{'s' * (counts[panel] > 2)}" if counts[panel] > 1 else ""
    return [
        FormatError(path, f"frames are {shape}, those of {shown(first)}{others} {panel}")
        for path, shape in shapes
        if shape != panel
    ]


def _in_given_order(errors, paths) -> list:
    """``errors`` sorted by where their file stands in ``paths`` (those naming none last)."""
    where = {str(p): i for i, p in reversed(list(enumerate(paths)))}
    return sorted(
        errors, key=lambda e: where.get(str(getattr(e, "path", None) or getattr(e, "filename", None)), len(paths))
    )


def _stack(
    paths, hints, key=None, progress=False, origins=None, bit_depths=None, layouts=None, scalings=None, inputs=None
) -> np.ndarray:
    """The frames of ``paths`` (those of image_key ``key`` where keyed) as one stack; ``origins``,
    when given, gets each frame's (file, index in it), ``bit_depths`` each file's declared ADC
    bits and whether they are signed (``meta["bit_depth"]`` and ``meta["bit_depth_signed"]``, None
    where it says nothing), ``layouts`` where each file's
    pixels lie on the sensor as read (:func:`radiokit.calibrate.pixel_layout`), ``scalings`` each
    file's :func:`radiokit.calibrate.value_scaling`, ``inputs`` each file's (and dataset's)
    :class:`radiokit.calibrate.CalibrationInput` (``hints["option"]``: the option that named its
    dataset), its frames of this kind counted (one file of darks and flats: one entry)."""
    from radiokit.calibrate import CalibrationInput, pixel_layout, value_scaling
    from radiokit.io import FormatError, check_budget, open_frames
    from radiokit.progress import tqdm

    frames, total, first = [], 0, None
    origins = [] if origins is None else origins
    what = "darks" if key == 2 else "flats" if key == 1 else "frames"
    kind = "darks" if key == 2 else "flats"  # (what an input's frames counted as)
    hints = dict(hints)
    option = hints.pop("option", None)
    with tqdm(desc=f"read {what}", unit="frame", disable=not progress) as bar:  # closed on an error too
        for p in paths:
            with open_frames(p, **hints) as src:
                if not len(src):  # as `radiokit info` says it
                    raise FormatError(p, "no frames")
                first = first or (p, src.frame_shape)
                if src.frame_shape != first[1]:  # np.stack would say only "must have the same shape"
                    raise FormatError(p, f"frames are {src.frame_shape}, those of {shown(first[0])} {first[1]}")
                total += len(src) * src.frame_bytes
                if bit_depths is not None:  # (and whether its counts are signed: a DICOM's word)
                    bit_depths[str(p)] = (src.meta.get("bit_depth"), src.meta.get("bit_depth_signed"))
                if scalings is not None:  # its values' scaling (a GDAL or CF file's): the level's unit
                    scalings[str(p)] = value_scaling(src.meta)
                if layouts is not None:
                    layouts[str(p)] = pixel_layout(src.meta)
                check_budget(p, total, f"the frames of {', '.join(map(shown, paths))}")
                keys = src.meta.get("image_key")
                # one entry per file and dataset: two datasets of one file (--dark-dataset d --flat-dataset f) are two
                where = (str(p), src.meta.get("dataset"))
                used = (
                    inputs.setdefault(where, CalibrationInput.of(p, src.meta, option)) if inputs is not None else None
                )
                for i in range(len(src)):
                    if key is None or keys is None or keys[i] == key:
                        frames.append(src[i])
                        origins.append((p, i))
                        if used is not None:
                            setattr(used, kind, getattr(used, kind) + 1)
                        bar.update()
                        if frames[-1].dtype.kind == "f" and not np.isfinite(frames[-1]).all():  # name where
                            raise FormatError(p, f"frame {i} holds NaN or inf; darks and flats must be finite")
    if not frames:  # every file has frames (above), none of them keyed as wanted
        names = {2: "darks (image_key 2)", 1: "flats (image_key 1)"}.get(key, "frames")
        raise ValueError(f"{', '.join(map(shown, paths))}: no {names} among their frames")
    return np.stack(frames)


def _hdf5_name(path) -> None:
    """An HDF5 output must be named so: under ``out.tif`` other programs would take it for a TIFF."""
    if Path(path).suffix.lower() not in (".h5", ".hdf5", ".hdf", ".nxs", ".nx"):
        raise ValueError(f"{shown(path)}: the output is HDF5; name it .h5 (or .hdf5, .nxs)")


def _declared(bits: dict, layouts: dict, scalings: dict) -> dict:
    """What the dark and flat files say of themselves, as :meth:`Calibration.from_frames` takes it:
    their bit depth (an experiment's, a TIFF's 12 or 14 bits; a DICOM's, signed or not) before the
    guess, where their pixels lie, and their values' scaling (a GDAL or CF file's: the saturation
    level's unit)."""
    from radiokit.calibrate import declared_bit_depth, declared_layout, declared_scaling, declared_signed

    return {
        "bit_depth": declared_bit_depth({name: depth for name, (depth, _) in bits.items()}),
        "signed": declared_signed({name: signed for name, (_, signed) in bits.items()}),
        "layout": declared_layout(layouts),
        "scaling": declared_scaling(scalings),
    }


def cmd_calibrate(args) -> int:
    from radiokit.calibrate import Calibration, line_summary
    from radiokit.io import atomic_path, check_output

    th = _parse_thresholds(args.threshold)
    inputs = [p for p in [args.experiment, *(args.dark or ()), *(args.flat or ())] if p]
    check_output(args.output, overwrite=args.overwrite, inputs=_inputs(args, inputs))  # before the work, not after
    _hdf5_name(args.output)
    if args.experiment and (args.dark or args.flat):  # the files given were silently not used
        raise ValueError("give --experiment FILE, or --dark FILES and --flat FILES, not both")
    kind = next((o for o in ("dark", "flat") if args.experiment and getattr(args, f"{o}_dataset", None)), None)
    if kind:  # so was the dataset named for them (s49rv)
        raise ValueError(
            f"--{kind}-dataset names the --{kind} files' dataset: give --dark and --flat files with it, not --experiment"
        )
    if args.experiment and getattr(args, "dataset", None):  # and --dataset: an experiment file's layout is its own
        raise ValueError(
            "--dataset names the --dark and --flat files' dataset: an --experiment file's darks and flats are "
            "told apart by its image_key (a plain stack of one kind: give it as --dark or --flat FILE with --dataset)"
        )
    if args.experiment:
        cal = Calibration.from_experiment(
            args.experiment,
            allow_external=args.allow_external,
            progress=_progress(args),
            narrow_frames=args.narrow_frames,
            **th,
        )
    else:
        if not (args.dark and args.flat):
            raise ValueError("give --dark FILES and --flat FILES, or --experiment FILE")
        cal = _calibration_from_files(args, th)
    # built in memory first: its size is then known, and a disk or file-size limit too small for
    # it is refused before the first byte (libhdf5 failing mid-write has crashed the interpreter)
    image = io.BytesIO()
    cal.save(image, name=args.output)
    with atomic_path(args.output, overwrite=args.overwrite, inputs=inputs, size_hint=len(image.getbuffer())) as tmp:
        tmp.write_bytes(image.getbuffer())
    p = cal.provenance
    print(
        f"calibration {cal.shape[0]}x{cal.shape[1]} from {p['n_darks']} darks and {p['n_flats']} flats -> {shown(args.output)}"
    )
    noise = p.get("dark_noise_counts")  # None from one dark: no temporal noise to measure (0.0 is a value)
    noise = "not measured (one dark)" if noise is None else f"{noise:.2f} counts"
    print(f"  c = mean(flat - dark) over valid pixels = {cal.c:.1f} counts; dark noise {noise}")
    print("  defects: " + ", ".join(f"{k} {v}" for k, v in p["defects"].items()))
    for what, text in line_summary(cal.defect_rows, cal.defect_columns, p).items():
        print(f"  {what}: {text}")
    return 0


def _refuse_unnameable(output, darks, flats) -> None:
    """Refuse, before any file is opened, dark and flat files more than the calibration's
    provenance can name (:func:`radiokit.calibrate.refuse_unnameable`): its ``dark_files``,
    ``flat_files`` and ``inputs`` (each file's name as given and resolved,
    :class:`radiokit.calibrate.CalibrationInput`) judged at their least (no format, dataset, size
    or time). Why: ``calibrate`` from ~13 000 files read every frame, then refused the save
    (review s53rvoff). A few more characters per file (the format, an HDF5 dataset's name) are
    judged exactly at the save, after the reading."""
    from radiokit.calibrate import CalibrationInput, refuse_unnameable

    files = list(dict.fromkeys(map(str, [*darks, *flats])))  # one file in both lists: one record at least
    least = {
        "dark_files": [str(p) for p in darks],
        "flat_files": [str(p) for p in flats],
        "inputs": [CalibrationInput(p, str(Path(p).resolve()), "", size_bytes=0).record() for p in files],
    }
    refuse_unnameable(f"{shown(output)}: not written", least, len(files))


def _calibration_from_files(args, th):
    """The calibration from ``--dark`` and ``--flat`` frame files, each kind read with its own
    hints (:func:`_dataset_hints`)."""
    from radiokit.calibrate import Calibration, FrameLevelError
    from radiokit.io import FormatError

    # a file given twice counted its frames twice: "3 darks" from 2, and the noise estimate
    # and the zinger rejection fed one frame as two. One file in both lists is allowed: an
    # experiment-style file holds darks and flats, told apart by image_key
    _refuse_repeats(args.dark, "--dark file", ": its frames would count twice")
    _refuse_repeats(args.flat, "--flat file", ": its frames would count twice")
    # --dark-dataset / --flat-dataset over --dataset: one dataset for both could not read two
    # HDF5 files of different layouts (s49off)
    datasets = _dataset_hints(args, {"dark": args.dark, "flat": args.flat})
    hints = {kind: _raw_hints(args) | datasets[kind] for kind in ("dark", "flat")}
    origins, bits, layouts, scalings, inputs = {"dark": [], "flat": []}, {}, {}, {}, {}
    _refuse_unnameable(args.output, args.dark, args.flat)
    _judge_files(args.dark, args.flat, hints["dark"], hints["flat"])
    # the option that named each kind's dataset, recorded with the files read (CalibrationInput)
    said = {k: f"--{k}-dataset" if getattr(args, f"{k}_dataset", None) else "--dataset" for k in ("dark", "flat")}
    said = {k: opt if datasets[k] else None for k, opt in said.items()}  # else the file's own layout
    files, image_key = {"dark": args.dark, "flat": args.flat}, {"dark": 2, "flat": 1}  # NXtomo's keys
    darks, flats = (
        _stack(
            files[k],
            hints[k] | {"option": said[k]},
            image_key[k],
            _progress(args),
            origins[k],
            bits,
            layouts,
            scalings,
            inputs,
        )
        for k in ("dark", "flat")
    )
    declared = _declared(bits, layouts, scalings)  # before averaging: darks and flats read alike
    if darks.shape[1:] != flats.shape[1:]:  # the library's message cannot name the files
        raise ValueError(
            f"flats {', '.join(map(shown, args.flat))} are {flats.shape[1:]}, "
            f"darks {', '.join(map(shown, args.dark))} {darks.shape[1:]}: one panel set-up, one frame size"
        )
    try:
        cal = Calibration.from_frames(darks, flats, progress=_progress(args), **declared, **th)
    except FrameLevelError as exc:  # the stack's index, named as the file's frame
        path, index = origins[exc.kind][exc.index]
        raise FormatError(path, f"frame {index} ({exc})") from exc
    except ValueError as exc:  # the library's "flats are not brighter than darks" names no file
        raise ValueError(
            f"darks {', '.join(map(shown, args.dark))}, flats {', '.join(map(shown, args.flat))}: {exc}"
            + _inverted_hint(files, hints)
        ) from exc
    cal.provenance["dark_files"] = [str(p) for p in args.dark]
    cal.provenance["flat_files"] = [str(p) for p in args.flat]
    cal.provenance["inputs"] = [one.record() for one in inputs.values()]
    return cal


def _inverted_hint(files: dict, hints: dict) -> str:
    """What a refused calibration's line adds where darks or flats are MONOCHROME1 DICOM (their
    lowest value shows white, read as stored). Why: such darks read above their flats, and the
    refusal blamed light on the panel. Only DICOM files are opened again (headers, no pixels),
    and only on a refusal."""
    from radiokit.io import open_frames, sniff

    inverted = []
    for kind, paths in files.items():
        for p in paths:
            if sniff(p) == "dicom":
                with open_frames(p, **hints[kind]) as src:
                    if src.meta.get("photometric") == "MONOCHROME1":
                        inverted.append(p)
    if not inverted:
        return ""
    return (
        f" ({', '.join(map(shown, dict.fromkeys(inverted)))} {'is' if len(inverted) == 1 else 'are'} MONOCHROME1, "
        "read as stored: higher values are less signal there; store them inverted as MONOCHROME2, "
        "2**BitsStored - 1 - value, and calibrate again)"
    )


# -- correct -----------------------------------------------------------------------------------
def _an_experiment(path, hints) -> None:
    """Without ``--cal`` the one file given calibrates itself, so it must hold darks and flats.
    Frames without them (a TIFF, a raw stack) were told "holds no darks (image_key 2): cannot
    calibrate", or, for a raw file given with ``--shape``, to pass ``--shape``: --cal is missing."""
    from radiokit.io import FormatError, ImageKey, open_frames

    with open_frames(path, **hints) as src:
        if not len(src):  # as `radiokit info` says it, not "not an experiment file"
            raise FormatError(path, "no frames")
        keys = np.asarray(src.meta.get("image_key", []))
    # an experiment file lacking one kind is told which by the calibration (review s34-r3)
    if not (np.any(keys == ImageKey.DARK) or np.any(keys == ImageKey.FLAT)):
        raise FormatError(
            path,
            "holds no darks and flats to calibrate from (not an experiment file): give --cal CAL.h5, "
            "made by radiokit calibrate --dark DARKS --flat FLATS",
        )


def cmd_correct(args) -> int:
    from radiokit.calibrate import Calibration
    from radiokit.correct import correct_files
    from radiokit.io import check_output

    check_output(args.output, overwrite=args.overwrite, inputs=_inputs(args, [*args.frames, args.cal]))
    if args.output.suffix.lower() not in (".h5", ".hdf5", ".nxs", ".tif", ".tiff"):  # before calibrating, not after
        raise ValueError(f"{shown(args.output)}: output must end in .h5/.hdf5/.nxs or .tif/.tiff")
    _refuse_repeats(args.frames, "frame file", ": its frames would be corrected twice into one stack")
    hints = _raw_hints(args) | _dataset_hints(args, {"frames": args.frames})["frames"]  # refused before the work
    if args.cal:
        cal = Calibration.load(args.cal)
    elif len(args.frames) == 1:
        _an_experiment(args.frames[0], hints)
        cal = Calibration.from_experiment(
            args.frames[0], allow_external=args.allow_external, narrow_frames=args.narrow_frames
        )
        print(f"calibrated from the darks and flats of {shown(args.frames[0])}")
    else:
        raise ValueError("--cal CAL.h5 is required unless a single experiment file is given")
    summary = correct_files(
        args.frames,
        cal,
        args.output,
        domain=args.domain,
        progress=_progress(args),
        overwrite=args.overwrite,
        **hints,
    )
    print(
        f"{summary['frames']} frame(s) -> {shown(summary['output'])} ({summary['domain']}) "
        f"at {summary['frames_per_second']:.1f} frames/s"
    )
    saturated = f"{summary['saturated']} saturated"
    if summary["saturated"] == "unknown":  # as info says it: never "0 saturated" of frames not checked
        saturated = f"saturation {summary['saturation_from']}"
    elif "saturation_from" in summary:  # some frames not checked: the count is of the others
        saturated += f" (saturation {summary['saturation_from']})"
    print(
        f"  flagged: {summary['defects_filled_per_frame']} defect pixels filled per frame; "
        # the count holds NaN and inf raw pixels too (PixelFlag.NONPOSITIVE): "non-positive" alone
        # said 100 NaN pixels were opaque
        f"{saturated}; {summary['nonpositive']} non-positive or non-finite (filled)"
    )
    return 0


# -- register ----------------------------------------------------------------------------------
def _one_image(path, index, hints, allow_external=False, option="--fixed-frame", narrow_frames=False):
    """Frame ``index`` of ``path`` (read with the reader's ``hints``: its dataset's) as float32, the
    index counted from the start (-1 is the last frame: the same-image check compares frames, not
    how they were written), and the file's metadata."""
    from radiokit.io import FormatError, open_frames

    hints = dict(hints) | ({"allow_external": True} if allow_external else {})
    hints |= {"narrow_frames": True} if narrow_frames else {}
    with open_frames(path, **hints) as src:  # one frame read, not the whole file
        if not len(src):  # as info, calibrate, correct and process say it (not "frame 0 requested")
            raise FormatError(path, "no frames")
        if not -len(src) <= index < len(src):
            raise ValueError(f"{shown(path)}: frame {index} requested, the file holds {len(src)}")
        _a_projection(path, src.meta.get("image_key"), index, option)
        image, index = src[index], index % len(src)
        meta = src.meta
    top = float(np.max(np.abs(image), initial=0, where=np.isfinite(image))) if image.dtype.kind == "f" else 0
    # cast, they became inf and were refused as NaN or inf in the file; compared as Python floats
    # (against numpy's float32 the comparison cast top, with an "overflow in cast" warning)
    if top > float(np.finfo(np.float32).max):
        raise ValueError(
            f"{shown(path)}: frame {index} holds values up to {top:.3g}, beyond float32's range, which registration uses"
        )
    return np.asarray(image, np.float32), index, meta


def _a_projection(path, keys, index, option) -> None:
    """An experiment file's frame 0 is a dark: `register exp.h5 ctl.h5` registered two darks and
    printed "NCC 1.0000 -> 1.0000" as if two radiographs had been. Only projections are taken."""
    if keys is None or int(np.asarray(keys)[index]) == 0:
        return
    key = int(np.asarray(keys)[index])
    kind = {1: "a flat", 2: "a dark", 3: "an invalid frame"}.get(key, f"image_key {key}")
    projections = np.flatnonzero(np.asarray(keys) == 0)
    which = f"the first projection is frame {projections[0]}" if projections.size else "the file holds no projection"
    raise ValueError(
        f"{shown(path)}: frame {index % len(keys)} is {kind} (image_key {key}), not a projection; {which} "
        f"({option} N picks one)"
    )


def _check_preset(args) -> None:
    """A ``--preset`` with a peer method is refused, not dropped (register) or a traceback (process),
    and so is register's ``--retry`` (a stronger B-spline regularisation: a peer ignored it)."""
    from radiokit.register import BSPLINE_METHODS

    if args.method in BSPLINE_METHODS:
        return
    for given, what in (
        (args.preset and f"--preset {args.preset}", "presets"),
        (getattr(args, "retry", False) and "--retry", "retries"),
    ):
        if given:
            raise ValueError(
                f"{given}: {what} are for the B-spline methods ({', '.join(BSPLINE_METHODS)}), not --method {args.method}"
            )


def _as_typed(bounds):
    """``--inclusion``/``--background``'s bounds (argparse's floats) as the user typed them, whole
    ones as ints, so Config's line echoes ``(10.5, 20, 10, 20)``, not ``[10.5, 20.0, 10.0, 20.0]``."""
    if bounds is None:
        return None
    return tuple(int(v) if math.isfinite(v) and v.is_integer() and abs(v) < 2**53 else v for v in bounds)


def _process_error(text, args, advice=None) -> str:
    """A ``Config`` or pipeline line in the command line's words: its fields as the options, a
    given ROI echoed as typed (``--inclusion 10.5 20 10 20``), ``roi_units='mm'`` as ``--mm``, and
    a reader's advice of an option process lacks (``advice``: :func:`_reader_advice`) as its own."""
    for field, option in _PROCESS_OPTIONS.items():
        if text.startswith(field):
            text = option + text[len(field) :]
    for name in ("inclusion", "background"):
        bounds = _as_typed(getattr(args, name, None))
        if bounds is not None:
            typed = f"--{name} {' '.join(str(v) for v in bounds)}"
            text = text.replace(f"{name} ROI {bounds!r}", typed).replace(f"--{name} {bounds!r}", typed)
    for option, said in (advice or {}).items():
        text = text.replace(said, _PROCESS_ADVICE.get(option, said))
    return text.replace("roi_units='mm'", "--mm")


def _reader_advice(exc) -> dict:
    """The reader options ``exc`` advises and its words for each (``FormatError.advice``), of
    each error of an ``InputErrors`` and of the error it was raised from too."""
    found, seen = {}, set()
    stack = [exc]
    while stack:
        e = stack.pop()
        if e is None or id(e) in seen:
            continue
        seen.add(id(e))
        for option, said in getattr(e, "advice", {}).items():  # the outermost error's words: those shown
            found.setdefault(option, said)
        stack += [*getattr(e, "errors", ()), e.__cause__, e.__context__]
    return found


#: what process says in place of a reader's advice (FormatError.advice) of an option it does not
#: have: it has no --allow-external (its inputs' links are not followed into its outputs' checks)
#: nor --dataset (it reads experiment files only)
_PROCESS_ADVICE = {
    "allow_external": "(radiokit process reads no data outside the experiment file: copy the linked data into it first)",
    "dataset": "radiokit process reads experiment files only (radiokit correct --dataset PATH reads one)",
    "narrow_frames": "radiokit process reads experiment files only, their frames stored (n, rows, cols)",
}


#: Config's field names as ``radiokit process`` spells them, for its one-line errors
_PROCESS_OPTIONS = {
    "ks=": "--k ",
    "crop_mm=": "--crop-mm ",
    "method=": "--method ",
    "cross_check=": "--cross-check ",
    "inclusion ROI ": "--inclusion ",
    "background ROI ": "--background ",
    "control=": "--control ",
}


def _register_inputs(args):
    """``register``'s two images and ``--roi`` mask, and its outputs checked: everything refused
    before the registration, not after it (an image against itself, a ROI off the image, an
    output onto an input, a figure matplotlib cannot write, a registration over the budget, two
    pixel sizes)."""
    from radiokit.io import check_output, check_same_pixel_size

    # --fixed-dataset / --moving-dataset over --dataset: two HDF5 files of different layouts (s38a)
    datasets = _dataset_hints(args, {"fixed": [args.fixed], "moving": [args.moving]})
    fixed, fixed_frame, fixed_meta = _one_image(
        args.fixed,
        args.fixed_frame,
        datasets["fixed"],
        args.allow_external,
        "--fixed-frame",
        args.narrow_frames,
    )
    moving, moving_frame, moving_meta = _one_image(
        args.moving,
        args.moving_frame,
        datasets["moving"],
        args.allow_external,
        "--moving-frame",
        args.narrow_frames,
    )
    # a field in pixels between two pitches is a scaling, not the sample's motion
    check_same_pixel_size(
        args.moving, moving_meta, args.fixed, fixed_meta, "register images of one pixel size (bin or resample one)"
    )
    # after the reads (a file that cannot be read says so first), before anything else is judged
    # the dataset each was read from: two datasets of one file (`pair.h5 pair.h5 --fixed-dataset
    # fix --moving-dataset mov`) are two images, which were refused as one
    fixed_ds, moving_ds = (str(m.get("dataset") or "").strip("/") for m in (fixed_meta, moving_meta))
    if fixed_frame == moving_frame and fixed_ds == moving_ds and _same_file(args.fixed, args.moving):
        # an image against itself: a zero field that says nothing (two frames of one file are fine)
        same = (
            shown(args.fixed)
            if str(args.fixed) == str(args.moving)
            else f"{shown(args.fixed)} and {shown(args.moving)}"
        )
        same += f", dataset {fixed_ds}" if fixed_ds else ""
        raise ValueError(
            f"{shown(args.moving)}: fixed and moving are the same image ({same}, frame {fixed_frame}); "
            "register one image onto another (--fixed-frame/--moving-frame pick frames of one file)"
        )
    mask = None
    if args.roi:
        r0, r1, c0, c1 = args.roi
        if not (r0 < r1 and c0 < c1):  # once told "must lie inside the image", which it did
            raise ValueError(f"--roi {args.roi}: an empty rectangle; expected R0 < R1 and C0 < C1")
        if not (0 <= r0 < r1 <= fixed.shape[0] and 0 <= c0 < c1 <= fixed.shape[1]):
            raise ValueError(f"--roi {args.roi}: must lie inside the {fixed.shape[0]}x{fixed.shape[1]} image")
        mask = np.zeros(fixed.shape, bool)
        mask[r0:r1, c0:c1] = True
    for out in (args.output, args.png):
        if out is not None:
            check_output(out, overwrite=args.overwrite, inputs=_inputs(args, [args.fixed, args.moving]))
    _hdf5_name(args.output)
    if args.png is not None and os.path.realpath(args.png) == os.path.realpath(args.output):
        raise ValueError(f"--png {shown(args.png)}: the same file as -o")
    if args.png is not None:  # matplotlib refused it only after the registration and -o were written
        from matplotlib.backend_bases import FigureCanvasBase

        kinds = FigureCanvasBase.get_supported_filetypes()
        if args.png.suffix.lower().lstrip(".") not in kinds:
            raise ValueError(
                f"--png {shown(args.png)}: name the figure .png (or {', '.join(f'.{k}' for k in sorted(kinds))})"
            )
    _check_register_memory(args, fixed)
    types = tuple(str(m.get("dtype", "")) for m in (fixed_meta, moving_meta))  # as stored
    return fixed, moving, mask, _types_hint(types, (fixed, moving))


#: register's peak memory per pixel of one image, beyond the interpreter's 250 MB, measured with
#: /usr/bin/time -v: rc --preset fast 51-53 bytes (476 MB at 2240 x 2240, 1.03 GB at 4000 x 4000,
#: 3.58 GB at 8000 x 8000), the default preset 63 (562 MB, 1.25 GB): 14-16 times the two uint16
#: images, which alone the reads held to the budget (8000 x 8000 under 200M peaked at 3.6 GB).
#: Session 49 measured each method at 1120 and 2240 px a side over a 64 px pair's peak
#: (benchmarks/README.md, "register's memory by method"): rc's default, ssd and ncc 84-93, tvl1,
#: dis and farneback 65-68, mi 78 at 2240 (a ~300 MB part of it does not grow with the pixels); the
#: methods above that have their own figure, the rest this one
REGISTER_BYTES_PER_PIXEL = 96
#: the methods whose peak is above REGISTER_BYTES_PER_PIXEL: ilk 142-144 bytes a pixel
REGISTER_BYTES_PER_PIXEL_OF = {"ilk": 150}


def _check_register_memory(args, fixed) -> None:
    """Refuse, before it starts, a registration whose working memory is over the budget."""
    from radiokit.io import BUDGET_ENV, human_bytes, memory_budget

    per_pixel = REGISTER_BYTES_PER_PIXEL_OF.get(args.method, REGISTER_BYTES_PER_PIXEL)
    need, limit = per_pixel * fixed.size, memory_budget()
    if need > limit:
        raise ValueError(
            f"fixed {shown(args.fixed)}, moving {shown(args.moving)}: registering two {fixed.shape[0]}x{fixed.shape[1]} images "
            f"{'' if args.method in (None, 'rc') else f'with {args.method} '}"
            f"needs about {human_bytes(need)} ({per_pixel} bytes a pixel), over the memory budget of "
            f"{human_bytes(limit)}: raise {BUDGET_ENV} if the machine has that memory, or register smaller "
            "images, cropped or binned beforehand (register has no crop of its own, and --roi narrows "
            "the score, not the images registered)"
        )


def cmd_register(args) -> int:
    from radiokit.io import RegistrationRecord
    from radiokit.register import register, with_default_preset

    fixed, moving, mask, types_hint = _register_inputs(args)
    _check_preset(args)
    options = {"preset": args.preset} if args.preset else {}
    # the B-spline methods run auto unless told (as radiokit process does): default, retried when flagged
    try:
        with _levels_bar(args, options) as options:
            reg = register(
                fixed,
                moving,
                args.method,
                mask,
                retry=args.retry,
                regularisation_check=args.regularisation_check,
                **with_default_preset(args.method, options),
            )
    except ValueError as exc:  # the library says "fixed" or "moving"; the user wants the file
        raise ValueError(f"fixed {shown(args.fixed)}, moving {shown(args.moving)}: {exc}") from exc
    q = reg.quality
    registered = reg.warp(moving)
    # the preset that made the field (auto's choice and why, what it started from), as
    # radiokit process records it: the file alone then says how to reproduce it
    quality = vars(q) | reg.run_record()
    record = RegistrationRecord(
        reg.method, str(args.fixed), str(args.moving), reg.displacement, registered, quality, reg.confidence
    )
    stopped = _write_register_outputs(args, record, lambda tmp: _register_png(tmp, fixed, moving, registered, reg))
    if stopped is not None:
        return stopped
    print(
        f"{reg.method}: {q.seconds:.2f} s, {q.iterations} iterations; residual complexity "
        f"{q.rc_before:.5g} -> {q.rc_after:.5g}, NCC {q.ncc_before:.4f} -> {q.ncc_after:.4f}; "
        f"folds {q.folds}, min det J {q.min_det_j:.3f}; max |d| {np.abs(reg.displacement).max():.2f} px"
    )
    if "auto" in reg.options:  # preset auto: what it returned, and why
        print(f"preset {reg.options['auto'].preset} ({reg.options['auto'].reason})")
    if "clipped" in reg.options:  # the field was measured on the pair with its extreme pixels clipped
        n = reg.options["clipped"]
        print(
            "clipped before registering, lying over ten of the pair's 0.1-99.9 % ranges beyond it (hot or "
            f"defective pixels?): {n['fixed']} pixels of {shown(args.fixed)}, {n['moving']} of {shown(args.moving)}"
        )
    if "regularisation_check" in reg.options:  # the second, differently regularised registration
        second = reg.options["regularisation_check"]
        print(
            f"regularisation check: rc {second['preset']} "
            + (
                f"differs by {q.disagreement:.2f} px over the interior"
                if second["run"]
                else "not run (already flagged)"
            )
        )
    print(f"wrote {shown(args.output)}" + _flag_warning(q, types_hint))
    if args.png:
        print(f"figure {shown(args.png)}")
    return 0 if q.ok else 1


def _write_register_outputs(args, record, draw) -> int | None:
    """``-o``'s field and ``--png``'s figure (``draw(temporary)``), each written into its
    temporary first (a stop or a refused figure meanwhile leaves both as they were), then both
    renamed into place as one step a stop cannot cut: one landing between the two renames (the
    field's folder fsync) left the new field beside the previous run's figure, and the command
    said "no partial output was left" (review s47rv3). A stop held over the renames is told once
    both are done, naming them; its exit status is returned (None: not stopped)."""
    from radiokit.interrupts import STOP_SIGNALS, exit_status, held, settle
    from radiokit.io import OutputError, atomic_path, remove_replaced, write_registration
    from radiokit.io._atomic import resolved

    inputs = [args.fixed, args.moving]
    with contextlib.ExitStack() as outputs:
        if args.png:
            figure = outputs.enter_context(atomic_path(args.png, overwrite=args.overwrite, inputs=inputs))
            draw(figure)
        tmp = outputs.enter_context(atomic_path(args.output, overwrite=args.overwrite, inputs=inputs))
        try:
            write_registration(tmp, record, overwrite=True, inputs=inputs)
        except OutputError as exc:  # (a read-only folder, a full disk) named as the user named it
            exc.path = str(args.output) if exc.path == str(tmp) else exc.path
            raise
        settle()  # a stop lost meanwhile: raised now, before anything is renamed
        renames = outputs.pop_all()
        if args.png:  # run first (last in): the previous figure goes before the field is renamed
            # a kill -9 between the renames then leaves a field without a figure, never the new
            # field beside the previous run's figure (session 48's leftover)
            # (checked as the renames check: what appeared at either name meanwhile is kept, s49rv)
            renames.callback(
                remove_replaced,
                figure.parent / Path(resolved(args.png)).name,
                figure,
                overwrite=args.overwrite,
                inputs=inputs,
                then=[tmp.parent / Path(resolved(args.output)).name],
            )
    done = False
    try:
        with held(*STOP_SIGNALS):
            renames.close()  # the field's rename, then the figure's
            done = True
    except KeyboardInterrupt as exc:
        if not done:
            raise
        both = f"{shown(args.output)} and {shown(args.png)} were" if args.png else f"{shown(args.output)} was"
        print(f"radiokit register: interrupted once {both} written (complete, this run's)", file=sys.stderr)
        return exit_status(exc)
    return None


#: NCC before registering below which a flagged pair is taken for each other's negative
_NEGATIVE_NCC = -0.5


def _negative_hint(q) -> str:
    """Why a flagged pair may be unregistrable as given: each other's negative (NCC well below 0
    before registering), the mark of two pixel conventions (line integrals, brighter where more
    attenuating, against counts or transmission, darker): no motion maps one onto the other, and
    the flag alone said "did not find the motion". (Mutual information aligns such a pair, but
    the checks, which compare intensities, flag it all the same.)"""
    if not q.ncc_before < _NEGATIVE_NCC:
        return ""
    return (
        f"; the images are each other's negative (NCC {q.ncc_before:.2f} before registering): one in line "
        "integrals -ln(I/I0), the other in counts or transmission? register two of one convention "
        "(radiokit correct --domain)"
    )


def _types_hint(types: tuple[str, str], images: tuple) -> str:
    """Why a flagged pair of integer images of two sizes (uint8 against uint16) may be judged
    unregistrable as given: an 8-bit copy of a 16-bit image (a viewer's export) holds its values
    about 257 times smaller, and the checks, which compare the registered pair's intensities with
    the noise, read that difference as structure left misaligned ("did not find the motion")
    whatever the field. s50: such a copy of one image, no motion, was registered by rc with a zero
    field (max |d| 0.00 px) and flagged; its 16-bit copy (x 257, quantised alike) was not. The
    flag stays: no check can judge intensities of two scales.

    Said only where the values show it: the wider image's (its 99.9th percentile, past a few hot
    pixels) lie beyond what the narrower type holds. The types alone said it of an 8-bit image
    against another widened to uint16 (ImageJ's "16-bit" keeps the values), one scale (s50rv1).
    ``types`` as stored, ``images`` (fixed, moving) as read."""
    kinds = [np.dtype(t) if t else None for t in types]
    if None in kinds or any(k.kind not in "ui" for k in kinds) or kinds[0].itemsize == kinds[1].itemsize:
        return ""
    narrow, wide = (0, 1) if kinds[0].itemsize < kinds[1].itemsize else (1, 0)
    values = np.asarray(images[wide], np.float64)
    values = values[np.isfinite(values)]
    if not values.size or np.percentile(values, 99.9) <= np.iinfo(kinds[narrow]).max:
        return ""
    bits = [8 * kinds[i].itemsize for i in (narrow, wide)]
    return (
        f"; the images are {kinds[0]} and {kinds[1]}: their values are not of one scale ({'an' if bits[0] == 8 else 'a'} {bits[0]}-bit copy of a "
        f"{bits[1]}-bit image?), which the checks compare; register two images of one type"
    )


def _flag_warning(q, types_hint) -> str:
    """The line ``register`` prints under a flagged result: the reason (which names two value
    ranges where the pair shows them, ``register()``'s), and what else the pair shows of why (each
    other's negative; two integer widths); "" when ok."""
    if q.ok:
        return ""
    return f"\nWARNING: not trustworthy: {q.reason}{_negative_hint(q)}{types_hint}"


@contextlib.contextmanager
def _levels_bar(args, options):
    """``options`` with a progress bar over the B-spline pyramid's levels (their callback: each
    level reports its factor and iterations; auto's second run and --retry count on). The flow
    peers take no callback and report nothing: ``options`` as given."""
    from radiokit.register import BSPLINE_METHODS

    if args.method not in BSPLINE_METHODS or not _progress(args):
        yield options
        return
    from radiokit.progress import tqdm

    with tqdm(desc=f"register {args.method}", unit="level") as bar:

        def level_done(factor, res):
            bar.set_postfix_str(f"1/{factor} scale, {int(res.nit)} iterations", refresh=False)
            bar.update()

        yield {**options, "callback": level_done}


#: the longest side an image is drawn at in register's figure: twice its panels' ~450 px
_FIGURE_SIDE = 1000


def _shrunk(image, step: int) -> np.ndarray:
    """``image`` averaged over ``step`` x ``step`` blocks (float32; the last rows and columns
    short of a block dropped), in bands of rows: no frame-sized temporary."""
    if step == 1:
        return np.asarray(image, np.float32)
    rows, cols = image.shape[0] // step, image.shape[1] // step
    out = np.empty((rows, cols), np.float32)
    for r in range(0, rows, 64):
        band = np.asarray(image[r * step : min(r + 64, rows) * step, : cols * step], np.float32)
        out[r : r + 64] = band.reshape(-1, step, cols, step).mean(axis=(1, 3))
    return out


def _register_png(path, fixed, moving, registered, reg):
    """The overlays before and after and det J, each averaged down to the figure's resolution
    first. Why: drawn at full resolution, two RGB float64 overlays and their temporaries took 25
    frames' worth (500 MB at 2240 x 2240) for panels of ~450 px, and doubled register's peak
    beyond what its memory check counts (s49off)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from radiokit.register import jacobian_determinant

    step = max(1, -(-max(fixed.shape) // _FIGURE_SIDE))
    if min(fixed.shape) < 2 * step:  # a strip: averaged blocks would leave nothing to draw
        step = 1
    fixed, moving, registered = (_shrunk(a, step) for a in (fixed, moving, registered))

    def norm(a):
        lo, hi = np.percentile(a, [1, 99])
        return np.clip((a - lo) / max(hi - lo, 1e-12), 0, 1)

    # constrained, not tight_layout: that left the square panels as tall as the figure, their
    # titles cut by its top edge
    fig, ax = plt.subplots(1, 3, figsize=(15, 5), layout="constrained")
    ax[0].imshow(np.dstack([norm(fixed), norm(moving), norm(fixed)]))
    ax[0].set_title("before: fixed magenta, moving green")
    ax[1].imshow(np.dstack([norm(fixed), norm(registered), norm(fixed)]))
    ax[1].set_title(f"after ({reg.method})")
    det = _shrunk(jacobian_determinant(reg.displacement), step)
    im = ax[2].imshow(det, cmap="RdBu_r", vmin=0.8, vmax=1.2)
    ax[2].set_title(f"det J (folds: {reg.quality.folds})")
    fig.colorbar(im, ax=ax[2], fraction=0.046)
    for a in ax:
        a.axis("off")
    fig.savefig(path, dpi=100)
    plt.close(fig)


def _process_config(args, opts):
    from radiokit.pipeline import Config

    return Config(
        ks=tuple(args.k),
        domain=args.domain,
        method=args.method,
        register_options=opts,
        crop_mm=args.crop_mm or None,
        inclusion=_as_typed(args.inclusion),
        background=_as_typed(args.background),
        roi_units="mm" if args.mm else "px",
        report=not args.no_report,
        progress=_progress(args),
        regularisation_check=args.regularisation_check,
        view=args.view,
        control=str(args.control) if args.control else None,
        cross_check=_cross_check(args),
    )


def _cross_check(args) -> str | None:
    """``--cross-check`` as Config takes it: ncc when not given (skipped where ncc is the method
    itself), None for none. The method itself, asked for, is refused: a second run of one method
    checks nothing, and Config skipped it without a word (a user read the run as cross-checked)."""
    if args.cross_check is None:
        return "ncc"
    if args.cross_check in ("none", ""):
        return None
    if args.cross_check == args.method:
        raise ValueError(
            f"--cross-check {args.cross_check}: the registration method itself (--method {args.method}); "
            "a second run of it checks nothing: name another method, or none"
        )
    return args.cross_check


#: names that say "a file": ``-o x.h5`` made a results folder called x.h5, which every other program
#: then takes for an HDF5 file
_DATA_SUFFIXES = (".h5", ".hdf5", ".hdf", ".nxs", ".nx", ".tif", ".tiff", ".json")


def _same_file(a, b) -> bool:
    """The same file however named: a symlink, a hard link, ``./a.h5`` (os.path.samefile
    compares device and inode); names that do not exist yet compare resolved."""
    try:
        return os.path.samefile(a, b)
    except OSError:
        from radiokit.io._atomic import resolved

        return resolved(a) == resolved(b)


def _refuse_repeats(files, what: str, why: str = "") -> None:
    """Refuse a file named twice in ``files`` (one line naming it, as given both ways when the names
    differ); a missing file is left to its own error, later."""
    for i, a in enumerate(files):
        for b in files[:i]:
            if os.path.exists(a) and _same_file(a, b):
                same = "twice" if str(a) == str(b) else f"as {shown(b)} and as {shown(a)}"
                raise ValueError(f"{shown(a)}: the same {what} given {same}{why}; give each file once")


def _check_process_files(args) -> None:
    """Refuse, before any work, what can only be a slip: a file given twice (it was processed
    twice, its folders STEM and STEM-2 holding the same numbers), a control that is one of the
    files (a control is another phantom, its inclusion as soft as the background: a file against
    itself compares nothing), and an ``-o`` named like a data file (it is a folder)."""
    _refuse_repeats(args.files, "experiment file")
    if args.control:
        for f in args.files:
            if _same_file(args.control, f):
                raise ValueError(
                    f"--control {shown(args.control)}: is the experiment file {shown(f)} itself; a control is another "
                    "experiment, its inclusion as soft as the background"
                )
    if args.output is not None and args.output.suffix.lower() in _DATA_SUFFIXES:
        raise ValueError(
            f"-o {shown(args.output)}: -o is a results folder, not a file; name it without {args.output.suffix} "
            "(results.h5, results.json and report.html are written inside)"
        )


def _check_process_memory(files, cfg, at_once: int = 1) -> None:
    """Refuse, before any work, a file whose processing would need more memory than the budget,
    as ``register`` refuses a registration: ``process`` registers the same frames and holds more
    (:func:`radiokit.pipeline.refuse_over_memory`). ``at_once`` files processed at once (the local
    cluster's workers) share the budget: each was checked against all of it, so two workers could
    take twice the budget."""
    from radiokit.io import BUDGET_ENV, human_bytes, memory_budget
    from radiokit.pipeline import refuse_over_memory

    limit = memory_budget()
    share = limit // max(1, at_once)
    budget = f"the memory budget of {human_bytes(limit)}" + (
        f" shared by the {at_once} files processed at once ({human_bytes(share)} each; --workers 1 takes one at a time)"
        if at_once > 1
        else ""
    )
    advice = (
        f": raise {BUDGET_ENV} if the machine has that memory, or process smaller frames, binned or cropped "
        "beforehand (--crop-mm narrows only what is kept)"
    )
    refuse_over_memory(files, cfg, share, budget + advice, control_name="--control ")


def cmd_process(args) -> int:
    # the checks of the command line and the files' names first: they need neither radiokit.pipeline
    # nor radiokit.register (scipy and more, 0.4 s), and a slip is refused before those load
    if args.workers is not None and args.workers < 1:
        raise ValueError(f"--workers {args.workers}: expected at least one worker")
    if not args.scheduler_timeout > 0:
        raise ValueError(f"--scheduler-timeout {args.scheduler_timeout:g}: expected a positive number of seconds")
    if not (np.isfinite(args.crop_mm) and args.crop_mm >= 0):  # Config's line says None, Python's 0
        raise ValueError(f"--crop-mm {args.crop_mm:g}: expected the crop's side in mm, > 0 (0: the whole frame)")
    if args.mm and not (args.inclusion or args.background):  # it was accepted and changed nothing
        raise ValueError("--mm: reads --inclusion and --background in mm; give one of them, or leave --mm out")
    missing = []  # every one named, each on its own line (InputErrors), not the first alone
    for f in [*args.files, *([args.control] if args.control else [])]:  # before the output checks name it
        if Path(f).is_dir():
            missing.append(ValueError(f"{shown(f)}: is a folder, not an experiment file"))
        elif not (Path(f).exists() or Path(f).is_symlink()):
            # said first: `process runs/*.h5 -o results` with no runs/ said "results: exists"
            where = "--control " if f == args.control else ""
            missing.append(ValueError(f"{where}{shown(f)}: no such experiment file"))
    if missing:
        from radiokit.errors import InputErrors

        raise missing[0] if len(missing) == 1 else InputErrors(missing)
    _check_process_files(args)
    if args.preset:  # it refuses only a preset given (with a peer method); it imports radiokit.register
        _check_preset(args)
    from radiokit._threads import cores
    from radiokit.io import check_output
    from radiokit.pipeline import local_workers, output_folders, process

    opts = {"preset": args.preset} if args.preset else {}
    try:
        cfg = _process_config(args, opts)
    except ValueError as exc:  # Config names its fields; the user typed the options
        raise ValueError(_process_error(str(exc), args)) from None
    inputs = [*args.files, *([args.control] if args.control else [])]
    single = len(args.files) == 1 and not args.scheduler
    outs = [args.output] if single and args.output else output_folders(args.files, args.output)
    for out in outs:  # refuse before any work, not after the first file
        check_output(out, overwrite=args.overwrite, inputs=inputs, folder=True)
    # the local cluster's workers each process a file at once; a scheduler's run on hosts only
    # process_many sees, which checks each file against its workers' share of their memory there
    if not args.scheduler:
        try:  # it opens each file first: a reader's refusal in process's words
            _check_process_memory(
                args.files, cfg, 1 if single else local_workers(args.workers, len(args.files), cores())
            )
        except ValueError as exc:
            text = _process_error(str(exc), args, _reader_advice(exc))
            if text == str(exc):
                raise
            raise ValueError(text) from exc
    if single:
        try:
            res = process(args.files[0], cfg, out_dir=outs[0], overwrite=args.overwrite)
        except ValueError as exc:  # as process_many reports each file's error: name the file
            text = _process_error(str(exc), args, _reader_advice(exc))
            # named already where it starts with a file (the control, say): a name anywhere in it was
            # taken for one, and a file named "the" was refused in a line naming none (review s51rv2)
            if any(text.startswith((f"{f}:", f"{shown(f)}:")) for f in inputs):
                if text == str(exc):
                    raise
                raise ValueError(text) from exc
            raise ValueError(f"{shown(args.files[0])}: {text}") from exc
        _print_headline(res.record, res.files, name=args.files[0], control=args.control)
        return 0 if _all_ok(res.record) else 1
    return _process_many(args, cfg)


def _process_many(args, cfg) -> int:
    """``radiokit process`` of many files, or of any on a scheduler: Dask, one headline per file."""
    from radiokit.pipeline import process_many
    from radiokit.results import Results

    if args.scheduler and not args.quiet:  # a dead address is a wait: say what it waits for, at once
        print(
            f"radiokit process: connecting to the Dask scheduler at {args.scheduler} "
            f"(waiting up to {args.scheduler_timeout:g} s)",
            file=sys.stderr,
            flush=True,
        )
    try:
        results = process_many(
            args.files,
            cfg,
            out_root=args.output,
            scheduler=args.scheduler,
            workers=args.workers,
            overwrite=args.overwrite,
            connect_timeout_s=args.scheduler_timeout,
        )
    except ValueError as exc:  # a refusal before any work (the workers' memory): in the options' words
        raise ValueError(_process_error(str(exc), args, _reader_advice(exc))) from None
    failed = 0
    for given, r in zip(args.files, results):  # (process_many's results: in the files' order)
        if "error" in r:
            failed += 1
            print(f"{shown(r['source'])}: error: {_batch_error(r, args)}", file=sys.stderr)
        else:
            files = {}
            if "output" in r:  # as one file's run prints them
                report = Path(r["output"]) / "report.html"
                files = {"report": str(report)} if report.exists() else {}
                files["results_json"] = str(Path(r["output"]) / "results.json")
            record = Results.from_json(r, r["source"])
            _print_headline(record, files, name=given, control=args.control)
            failed += not _all_ok(record)  # as one file's run: a flagged pair is exit 1
    return 1 if failed else 0


def _batch_error(result, args=None) -> str:
    """A failed file's words in ``process_many``'s results as one file's run prints them: the
    options' names, ``--overwrite`` for the API's ``--overwrite (overwrite=True)``."""
    from radiokit.io import OutputExistsError

    text = _process_error(result["error"], args, result.get("advice")).replace(OutputExistsError.HOW, "--overwrite")
    return _one_line(text, _given_names(args) if args else ())  # one line, as _error_line's


def _all_ok(record) -> bool:
    """Every registration of the file's run passed its checks, the control's too: its numbers are
    what the file's are judged against."""
    return all(p.ok for p in record.pairs) and (record.control is None or _all_ok(record.control))


def _print_headline(record, files, prefix="", *, name=None, control=None):
    """The lines ``radiokit process`` prints for one file (:class:`radiokit.results.Results`), and
    for its control after them (``prefix`` "control "); the domains by radiokit's names
    (``negative`` is -I/I0, the paper's "linear" images; DESIGN.md keeps "linear" for I/I0).

    ``name``, ``control``: the file and its control as the command was given them, named so.
    Why not ``record.source``: it is the name as UTF-8 text, a byte that is not UTF-8 written
    ``\\xNN`` with a real backslash, which names print quoted and doubled, ``'exp\\\\xe9.h5'``:
    another file, one named with a backslash (review s52rvoff)."""
    from radiokit.results import k_label, sig3, value_pm

    dom = record.domain
    ifs = ", ".join(
        f"k={k_label(x.k)}: {value_pm(x.improvement_factor, x.improvement_factor_se)}"
        for x in record.domains[dom].per_k
    )
    main = record.pair(record.main_pair)
    reason = (main.change_ratio_reason or {}).get(dom)
    cr = reason if reason else value_pm(main.change_ratio[dom], (main.change_ratio_se or {}).get(dom), 3)
    print(
        f"{prefix}{shown(record.source if name is None else name)}: improvement factor ({dom.value}) {ifs}; change ratio {main.name} "
        f"{cr}; registration {'ok' if main.ok else 'NOT ok: ' + main.reason}"
    )
    for dom, m in record.domains.items():  # every k and domain: IF (bound), CNR
        parts = [
            f"k={k_label(x.k)}: IF {value_pm(x.improvement_factor, x.improvement_factor_se, 3)}"
            + (f" (bound {x.bound:.3f})" if x.bound is not None else "")
            + f", CNR {sig3(x.cnr)}"
            for x in m.per_k
        ]
        print(f"  {dom.value:<8}: CNR reference {sig3(m.cnr_reference)}; " + "; ".join(parts))
    # the exit code is 1 when any pair is flagged: say which, or "registration ok" above was all
    # a user saw of a run that exited 1 (the main pair was fine, 1->3 was not)
    for pair in record.pairs:
        if not pair.ok and pair.name != main.name:
            print(f"  WARNING: pair {pair.name} NOT ok: {pair.reason}")
    if record.control is not None:  # it was in results.json and the report only
        _print_headline(record.control, {}, prefix="control ", name=control)
    for name in ("report", "results_json"):
        if name in files:
            print(f"  {name.replace('_', '.')}: {shown(files[name])}")


# -- parser ------------------------------------------------------------------------------------
def _add_info(sub):
    p = sub.add_parser(
        "info",
        help="describe frame files (format, geometry, range, metadata)",
        description="Describe frame files: format, frames x rows x cols, pixel type, value range, saturated "
        "and NaN/inf pixels (in --sample evenly spaced frames) and the metadata that matters.",
    )
    p.add_argument(
        "files",
        nargs="+",
        type=Path,
        help="frame files: raw (headerless 16-bit, geometry from --preset or --shape, or the size where only one fits), TIFF, HDF5 (radiokit's files; others with --dataset), Hamamatsu ITEX .img, greyscale PNG, JPEG, JPEG 2000 or DICOM",
    )
    p.add_argument("--json", action="store_true", help="print JSON")
    p.add_argument(
        "--sample",
        type=int,
        default=None,  # 8; None tells an explicit --sample from the default, which --all refuses
        metavar="N",
        help="frames read for the range and saturation, evenly spaced (default 8)",
    )
    p.add_argument("--all", action="store_true", help="read every frame for the range and saturation")
    _add_raw_hints(p)
    p.set_defaults(func=cmd_info)


def _add_calibrate(sub):
    p = sub.add_parser(
        "calibrate",
        help="build a dark/flat/defect calibration",
        description="Average darks (beam off) and flats (open beam, phantom out) and classify defective "
        "pixels and lines, from frame files or from an experiment file's own darks and flats.",
    )
    p.add_argument(
        "--dark",
        nargs="+",
        type=Path,
        help="dark (beam off) frame files: raw (headerless 16-bit, geometry from --preset or --shape, or the size where only one fits), TIFF, HDF5 (radiokit's files; others with --dataset), Hamamatsu ITEX .img, greyscale PNG, JPEG, JPEG 2000 or DICOM",
    )
    p.add_argument("--flat", nargs="+", type=Path, help="flat (open beam, no phantom) frame files, as --dark")
    p.add_argument("--experiment", type=Path, help="take darks and flats from an experiment file")
    p.add_argument(
        "--threshold",
        action="append",
        metavar="NAME=VALUE",
        help="a defect threshold, repeatable: dead_below, under_below, over_above (relative response), "
        "noisy_factor, line_deviation, line_noise_factor, line_fraction, clip_sigma, eps (counts), "
        "saturation (ADC value; default: the bit depth the files declare, else 255 for 8-bit frames, else the top of the 12-, 14- or 16-bit range the darks and flats fit, or 1023 where they pile up there), smooth_block (px); radiokit.calibrate.Thresholds has each "
        "default",
    )
    p.add_argument("-o", "--output", type=Path, required=True, help="calibration file (.h5)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing output (never an input)")
    p.add_argument(
        "-q", "--quiet", action="store_true", help="no progress bars (none either when stderr is not a terminal)"
    )
    _add_raw_hints(p)
    g = next(g for g in p._action_groups if g.title == "HDF5 files of other layouts")
    # one --dataset for both kinds could not read two HDF5 files of different layouts (s49off)
    g.add_argument("--dark-dataset", help="the dark files' HDF5 dataset (instead of --dataset for them)")
    g.add_argument("--flat-dataset", help="the flat files' HDF5 dataset (instead of --dataset for them)")
    p.set_defaults(func=cmd_calibrate)


def _add_correct(sub):
    p = sub.add_parser(
        "correct",
        help="dark/flat/defect-correct frames to transmission or line integral",
        description="Correct frames with a calibration (offset, gain, defect pixels and lines filled and "
        "flagged) to line integrals -ln(I/I0), transmission I/I0 or gain-corrected counts, streamed frame by "
        "frame into one HDF5 or TIFF stack.",
    )
    p.add_argument(
        "frames",
        nargs="+",
        type=Path,
        help="frame files (raw (headerless 16-bit, geometry from --preset or --shape, or the size where only one fits), TIFF, HDF5 (radiokit's files; others with --dataset), Hamamatsu ITEX .img, greyscale PNG, JPEG, JPEG 2000 or DICOM), or one experiment file without --cal",
    )
    p.add_argument("--cal", type=Path, help="calibration file (default: from the experiment file's darks and flats)")
    p.add_argument(
        "--domain",
        choices=["log", "linear", "counts"],
        default="log",
        help="log: -ln(I/I0) (default); linear: I/I0; counts: the manual's gain-corrected grey levels",
    )
    p.add_argument("-o", "--output", type=Path, required=True, help="output .h5 or .tif")
    p.add_argument("--overwrite", action="store_true", help="replace an existing output (never an input)")
    p.add_argument(
        "-q", "--quiet", action="store_true", help="no progress bar (none either when stderr is not a terminal)"
    )
    _add_raw_hints(p)
    p.set_defaults(func=cmd_correct)


def _add_register_checks(p):
    """``radiokit register``'s second tries: ``--retry`` and ``--regularisation-check``."""
    p.add_argument(
        "--retry",
        action="store_true",
        help="B-spline methods: retry a registration flagged not ok with 10x stronger regularisation",
    )
    p.add_argument(
        "--regularisation-check",
        action="store_true",
        help="register again, differently regularised (rc weak at 0.1 Mpx), and flag a trusted result that "
        "differs from it by over 0.6 px inside the object (0.3-1 s more)",
    )


def _add_register_inputs(p):
    """``radiokit register``'s choice of frames and datasets in its two files."""
    p.add_argument(
        "--fixed-frame",
        type=int,
        default=0,
        help="frame index in a multi-frame fixed file (default 0; of an experiment file, a projection)",
    )
    p.add_argument(
        "--moving-frame",
        type=int,
        default=0,
        help="frame index in a multi-frame moving file (default 0; of an experiment file, a projection)",
    )
    g = p.add_argument_group("HDF5 files of other layouts", _DATASET_RULE)
    g.add_argument(
        "--dataset",
        help="HDF5 dataset holding the frames of both images (e.g. entry/data/data of `radiokit correct`); "
        "--fixed-dataset / --moving-dataset name one image's",
    )
    # one --dataset for both: two HDF5 files of different layouts could not be registered at all
    g.add_argument("--fixed-dataset", help="the fixed image's HDF5 dataset (instead of --dataset for it)")
    g.add_argument("--moving-dataset", help="the moving image's HDF5 dataset (instead of --dataset for it)")
    p.add_argument(
        "--allow-external",
        action="store_true",
        help="read data in other files: HDF5 links and storage, a multi-file OME-TIFF's other files",
    )
    p.add_argument("--narrow-frames", action="store_true", help=_NARROW_HELP)


def _add_register(sub):
    p = sub.add_parser(
        "register",
        help="non-rigid registration of MOVING onto FIXED (residual complexity by default)",
        description="Register one frame of MOVING onto one of FIXED; write the pull field (pixels, (row, col)), "
        "the registered image and the quality checks. Exit code 1 when the result is flagged not ok.",
    )
    p.add_argument(
        "fixed",
        type=Path,
        help="fixed image file: TIFF, HDF5 or any format `radiokit info` reads (e.g. a line-integral frame "
        "from `radiokit correct --domain log`)",
    )
    p.add_argument("moving", type=Path, help="moving image file, of the fixed image's size")
    p.add_argument(
        "--method", default="rc", help="rc (default), ssd, ncc, mi, or a peer: tvl1, ilk, dis, farneback, ..."
    )
    p.add_argument(
        "--preset",
        choices=PRESET_NAMES,
        help="B-spline methods: default, fast, weak / weak-fast (texture near the noise level), silent / "
        "silent-fast (a textureless body: starts from the silhouettes' affine map, stiff lattices), or auto / "
        "auto-fast (default, retried when flagged: with weak on a textured interior, silent on a silent body; "
        "the default)",
    )
    p.add_argument(
        "--roi",
        type=int,
        nargs=4,
        metavar=("R0", "R1", "C0", "C1"),
        help="score the similarity only inside rows R0:R1, columns C0:C1",
    )
    _add_register_inputs(p)
    _add_register_checks(p)
    p.add_argument(
        "-o", "--output", type=Path, required=True, help="result file (.h5): field, registered image, quality"
    )
    p.add_argument("--png", type=Path, help="also write an overlay and det J figure (.png, .pdf, .svg, ...)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing output (never an input)")
    p.add_argument(
        "-q", "--quiet", action="store_true", help="no progress bar (none either when stderr is not a terminal)"
    )
    p.set_defaults(func=cmd_register)


def _add_process(sub):
    p = sub.add_parser(
        "process",
        help="experiment file(s) -> registered steps, compression-induced contrast, measurements, report",
        description="Calibrate, correct, register every step onto the most compressed, enhance "
        "(k = 1, 2), measure and report. Several files run in parallel on Dask.",
    )
    p.add_argument("files", nargs="+", type=Path, help="experiment files (.h5)")
    p.add_argument(
        "-o",
        "--output",
        type=Path,
        help="results folder of one file; with several files, the folder holding one per file, named "
        "after it (STEM, then STEM-2 ... when names repeat); default: beside each file",
    )
    p.add_argument(
        "--overwrite",
        action="store_true",
        help="replace an existing results folder radiokit made (never one holding an input)",
    )
    p.add_argument(
        "--k", type=float, nargs="+", default=[1.0, 2.0], help="enhancement factors, each in (0, 100] (default 1 2)"
    )
    p.add_argument(
        "--domain",
        choices=["negative", "log"],
        default="negative",
        help="headline domain: negative (-I/I0, the paper's 'linear' images; default) or log "
        "(-ln(I/I0)); both are computed",
    )
    p.add_argument("--method", default="rc", help="registration method (default rc)")
    p.add_argument(
        "--preset",
        choices=PRESET_NAMES,
        help="registration preset (see `radiokit register --help`; default for the B-spline methods: auto)",
    )
    p.add_argument(
        "--crop-mm",
        type=float,
        default=30.0,
        help="side of the square around the inclusion kept in the outputs, mm, widened to hold both ROIs "
        "(default 30; 0, or more than the frame: the whole frame)",
    )
    p.add_argument(
        "--inclusion",
        type=float,
        nargs=4,
        metavar=("R0", "R1", "C0", "C1"),
        help="inclusion rectangle: rows R0:R1, columns C0:C1, half-open, in whole pixels of the full frame "
        "(with --mm: millimetres, any number, rounded to pixels) (default: found automatically)",
    )
    p.add_argument(
        "--background",
        type=float,
        nargs=4,
        metavar=("R0", "R1", "C0", "C1"),
        help="background rectangle, as --inclusion (default: beside the inclusion)",
    )
    _add_process_options(p)
    p.set_defaults(func=cmd_process)


def _add_process_options(p):
    """The process options beyond the science: ROI units, control, report, cross-check, Dask."""
    p.add_argument(
        "--mm",
        action="store_true",
        help="rectangles in mm from the frame's top-left corner (any number, rounded to pixels), not whole pixels",
    )
    p.add_argument("--control", type=Path, help="a control experiment (inclusion as soft as the background)")
    p.add_argument("--no-report", action="store_true", help="results.h5 and results.json only")
    p.add_argument(
        "--cross-check",
        help="register the main pair again with this method and flag a disagreement (default ncc; 'none' to skip)",
    )
    p.add_argument(
        "--regularisation-check",
        action="store_true",
        help="register every pair again, differently regularised, and flag a trusted result the two disagree on "
        "(0.3-1 s more per pair)",
    )
    p.add_argument(
        "--view",
        choices=("through_plates", "side"),
        help="the beam's direction, for the improvement factor's bound: through the plates (the default for "
        "a file that records no simulated scene) or from the side (no bound holds); a --control takes the "
        "experiment's",
    )
    p.add_argument("--scheduler", help="Dask scheduler address for many files (default: a local cluster)")
    p.add_argument(
        "--scheduler-timeout",
        type=float,
        default=10.0,
        metavar="SECONDS",
        help="how long to wait for --scheduler to answer (default 10 s)",
    )
    p.add_argument("--workers", type=int, help="local Dask workers (default: one per core; never more than the files)")
    p.add_argument(
        "-q", "--quiet", action="store_true", help="no progress bars (none either when stderr is not a terminal)"
    )


class _Parser(argparse.ArgumentParser):
    """argparse's parser whose usage errors are one line, as every other error (argparse printed
    the whole usage, up to eight lines, above it); the subcommands' parsers are of this class too."""

    def error(self, message):
        self.exit(2, f"{self.prog}: {' '.join(message.split())} (see {self.prog} --help)\n")

    def parse_known_args(self, args=None, namespace=None):
        namespace, extras = super().parse_known_args(args, namespace)
        # the innermost parser with arguments it does not know finishes first: it names itself
        # and them, and the outer ones keep that (their own extras come on top of it)
        if extras and not hasattr(namespace, "_radiokit_unknown"):
            namespace._radiokit_unknown = (self, list(extras))
        return namespace, extras

    def parse_args(self, args=None, namespace=None):
        # an option the subcommand does not know is its error, not the top level's: "radiokit:
        # unrecognized arguments: --overwirte (see radiokit --help)" pointed at the wrong help;
        # one given to an outer level (`radiokit --bogus process`) stays that level's
        namespace, extras = self.parse_known_args(args, namespace)
        parser, theirs = vars(namespace).pop("_radiokit_unknown", (self, []))
        if extras:
            (parser if sorted(theirs) == sorted(extras) else self).error(f"unrecognized arguments: {' '.join(extras)}")
        return namespace


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="radiokit", description="X-ray radiography for elasticity-contrast studies.")
    parser.add_argument("--version", action="version", version=f"radiokit {__version__}")
    parser.add_argument("--debug", action="store_true", help="show tracebacks on errors")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for add in (_add_info, _add_calibrate, _add_correct, _add_register, _add_process):
        add(sub)
    for ep in sorted(entry_points(group="radiokit.commands"), key=lambda e: e.name):
        ep.load()(sub)
    return parser


def _terminated(signum, frame):
    """Ctrl-C, SIGTERM/SIGHUP/SIGQUIT (a closed terminal, ``kill``, Ctrl-\\): unwind, so that every output being
    written is removed rather than left half-written under its temporary name. Should it land in
    a finalizer, where Python drops it, ``_main`` delivers it again (radiokit.interrupts)."""
    from radiokit.interrupts import Interrupted, after_import

    if after_import(signum, frame):  # raised inside an import, a library's bare except swallowed it
        return
    raise Interrupted(signum)


def _interrupted(exc) -> KeyboardInterrupt | None:
    """The interrupt behind ``exc`` (itself, or one a library turned into its own error)."""
    while exc is not None:
        if isinstance(exc, KeyboardInterrupt):
            return exc
        exc = exc.__cause__ or exc.__context__
    return None


def _user_error(exc) -> bool:
    """Errors a user causes (a file, a parameter, the disk, the memory), or an interrupt some
    library re-raised as its own error; anything else is a bug and keeps its traceback."""
    return isinstance(exc, (RadiokitError, ValueError, OSError, MemoryError)) or _interrupted(exc) is not None


def _stdout_gone() -> bool:
    """stdout is a pipe whose reader has closed it (poll reports POLLERR); then stdout points at
    /dev/null, so that the interpreter's last flush does not fail again (Python's recipe)."""
    import select

    try:
        fd = sys.stdout.fileno()
        poller = select.poll()
        poller.register(fd, select.POLLOUT)
        if not any(events & select.POLLERR for _, events in poller.poll(0)):
            return False
        os.dup2(os.open(os.devnull, os.O_WRONLY), fd)
        return True
    except (AttributeError, ValueError, OSError):  # no stdout, not a file, or no poll (Windows)
        return False


def _debug(args) -> bool:
    return bool(getattr(args, "debug", False) or os.environ.get("RADIOKIT_DEBUG", "") not in ("", "0"))


def _names_as_bytes(exc: UnicodeEncodeError):
    """Codec error handler for the command's output: a file name's bytes that are not UTF-8 (a
    Latin-1 name; Python holds them as lone surrogates) print as ``\\xNN``, as radiokit records
    them in its files, and any other character the terminal cannot show as ``\\uNNNN``.

    Why: under a UTF-8 locale stdout is strict, and printing such a name after the work (``-> o\\xfe.h5``)
    failed the command with exit code 2 although its output had been written."""
    bad = exc.object[exc.start : exc.end]
    return (
        "".join(
            f"\\x{ord(ch) - 0xDC00:02x}"
            if 0xDC80 <= ord(ch) <= 0xDCFF
            else ch.encode("ascii", "backslashreplace").decode()
            for ch in bad
        ),
        exc.end,
    )


codecs.register_error("radiokit-names", _names_as_bytes)


@contextlib.contextmanager
def _printable_names():
    """stdout and stderr print any file name (see :func:`_names_as_bytes`); restored afterwards
    (``main`` also runs inside other programs and tests)."""
    before = []
    for stream in (sys.stdout, sys.stderr):
        try:
            before.append((stream, stream.errors))
            stream.reconfigure(errors="radiokit-names")
        except (AttributeError, ValueError, OSError):  # not a text stream that can be reconfigured
            before.pop()
    try:
        yield
    finally:
        for stream, errors in before:
            try:
                stream.reconfigure(errors=errors)
            except (AttributeError, ValueError, OSError):
                pass


def main(argv=None) -> int:
    """Run a subcommand. A user-caused error (a bad file, parameter or output; a full disk) is
    one line ``radiokit CMD: FILE: PROBLEM`` on stderr and exit code 2; anything else is a bug
    and keeps its traceback. ``--debug`` or ``RADIOKIT_DEBUG=1`` shows tracebacks for all."""
    with _printable_names():
        with _signals_given_back(True):
            code = _main(argv)
        return _stopped_after_the_end(code)  # read once the caller's handlers are back: none lost


def script() -> int:
    """The ``radiokit`` console script: :func:`main` on the command line's arguments, except that
    a finished ``acquire`` leaves the stop signals recorded, then ignored, until the process
    exits (see :func:`_signals_given_back` and :class:`_AtTheExit`). Only for a process that ends
    as it returns: a Python program that goes on calls :func:`main`, which gives its handlers
    back however it ends."""
    import atexit

    global _AT_THE_EXIT
    if _AT_THE_EXIT is not None:  # script() run again in one process (tests): one hook, the last command's
        atexit.unregister(_AT_THE_EXIT)
    # registered before the command imports anything: atexit runs the last registered first, so
    # this runs after every other callback, as late as Python code runs
    _AT_THE_EXIT = _AtTheExit()
    atexit.register(_AT_THE_EXIT)
    with _printable_names():
        with _signals_given_back(False):
            code = _main(None)
        code = _stopped_after_the_end(code)
        _AT_THE_EXIT.armed(code)
        return code


class _AtTheExit:
    """The console script's last Python code (an ``atexit`` callback, run after every other), for
    a source action whose guard left the stop signals recorded (its ``finish``): the exit code
    with any stop recorded since ``script()`` returned (0 becomes 128 + N), given by
    ``os._exit`` after the flushes -- the interpreter's own end is skipped.

    Why: measured, a source command lived 20-45 ms after its last ``atexit`` callback (Python
    tearing its modules down), against 0-1 ms from its outcome to ``script()``'s return: the
    reviewer's 31-145 ms window was that end. No Python handler runs there, and Python's
    finalization sets one back to the default (a Ctrl-C then ended the process by SIGINT,
    review s49), so they were ignored, and a Ctrl-C there was lost: exit 0, and `probe && source
    on` switched X-rays on after it (review of s52). Nothing is left to tear down: the port is
    closed, the guardian gone, no file written. Other commands end as Python ends them."""

    def __init__(self):
        self.code: int | None = None
        self.record: list[int] | None = None

    def armed(self, code: int) -> None:
        interrupts = sys.modules.get("radiokit.interrupts")
        if interrupts is not None:
            self.code, self.record = code, interrupts.stops_after_the_end()

    def __call__(self) -> None:
        interrupts = sys.modules.get("radiokit.interrupts")
        # another command since (main() in the same process) or none armed: not this hook's
        if self.record is None or interrupts is None or interrupts.stops_after_the_end() is not self.record:
            return
        recording = [sig for sig in _TAKEN if signal.getsignal(sig) is interrupts.note_after_the_end]
        if not recording or not _on_main_thread():  # not a source action's end (or its handlers given back)
            return
        for sig in recording:
            # (signal.signal runs a handler still pending before it changes it: it is recorded)
            signal.signal(sig, signal.SIG_IGN)
        code = _stopped_after_the_end(self.code)
        logging.shutdown()  # (registered before this hook: it would have run after it)
        for stream in (sys.stdout, sys.stderr):
            with contextlib.suppress(Exception):
                stream.flush()
        os._exit(code)


#: the console script's hook, the last script() call's (tests run several in one process)
_AT_THE_EXIT: _AtTheExit | None = None


def _stopped_after_the_end(code: int) -> int:
    """``code``, or 128 + N where it is 0 and stop signal N came after the command's outcome was
    decided (an ``acquire source`` action's guard's ``finish``: recorded, not acted on, by
    :func:`radiokit.interrupts.note_after_the_end`). Why: ignored, a Ctrl-C in a probe's last
    30-150 ms was lost and exit 0 let `probe && source on` switch X-rays on after it (review of
    s52). Any other code stays: 3 (the tube not confirmed off) and 2 say more than the stop."""
    interrupts = sys.modules.get("radiokit.interrupts")  # not imported: no command ran (its import was stopped)
    signum = interrupts.stop_after_the_end() if interrupts is not None else None
    return 128 + signum if code == 0 and signum is not None else code


#: The signals a command may take over (radiokit.interrupts.STOP_SIGNALS, and acquire's Ctrl-Z).
_TAKEN = tuple(
    getattr(signal, name) for name in ("SIGINT", "SIGTERM", "SIGHUP", "SIGQUIT", "SIGTSTP") if hasattr(signal, name)
)


@contextlib.contextmanager
def _signals_given_back(give: bool):
    """With ``give`` (:func:`main`, called from a Python program, which goes on after it, with or
    without argv), the signals' handlers put back as they were found: a lab script calling
    ``main()`` with no argv was left with Ctrl-C and kill ignored (session 52). Not for the console
    script (:func:`script`), whose process ends as it returns: a finished ``acquire`` leaves them
    ignored until the process exits (its guard's ``finish``), since Python's own finalization
    turns a Python handler back into the default action, and a Ctrl-C then ended a complete
    series by SIGINT. A source action's guard leaves them recorded (its ``finish``), to the
    console script's exit (:class:`_AtTheExit`)."""
    found = {}
    if give and _on_main_thread():
        found = {sig: signal.getsignal(sig) for sig in _TAKEN}
    try:
        yield
    finally:
        if found:
            _give_back({sig: handler for sig, handler in found.items() if handler is not None})


def _give_back(found: dict) -> None:
    """Put the caller's handlers ``found`` back, all of them, a stop landing meanwhile delivered to
    the caller's handler once they all are back (session 53). Why: put back one by one, a Ctrl-C
    landing midway ran the caller's handler there (Python's raises) and cut the loop short, so the
    handlers after it stayed the command's -- acquire's records a stop and does nothing else -- and
    the lab script could no longer be stopped by kill; one landing on a handler not yet put back
    went to the command's, which had finished.

    The signals are blocked in this thread (``pthread_sigmask``) while the handlers are set: one
    sent then waits in the kernel (Linux keeps a blocked signal pending even where it is ignored)
    and is delivered as they are unblocked, to the handler now in place. Blocking holds off only
    this thread's delivery: a signal taken by another thread of the caller's, or one that reached
    Python just before the block, runs the handler in place at the next check and may raise here;
    the handlers are then set all the same and its exception raised after them (the first, if
    several). Two at once are held; a third at once may leave a handler unset (Python code cannot
    hold any number together), but never a signal blocked."""
    if not hasattr(signal, "pthread_sigmask"):  # Windows: nothing to block with
        _give_back_unmasked(found)
        return
    taken = set(found)
    blocked = None  # the taken signals the caller had blocked already: left blocked
    error: BaseException | None = None
    todo = list(found.items())
    try:
        while True:
            try:
                if blocked is None:
                    blocked = signal.pthread_sigmask(signal.SIG_BLOCK, ()) & taken  # (reads the mask only)
                signal.pthread_sigmask(signal.SIG_BLOCK, taken)
                while todo:
                    signal.signal(*todo[0])  # set again if the raise below lands after it: the same handler
                    del todo[0]
                break
            except BaseException as exc:  # a handler in place ran (see above) and raised: carry on, raise it after
                error = error or exc
    finally:
        # Python runs a handler where its loop jumps back too, outside the try above: a second
        # stop noted with the first (two at once: a Ctrl-C and a kill) raised there and left the
        # give-back midway, the signals blocked in this thread for good (review s53rvacq). The
        # handlers left are put back here; nothing runs a handler between a raise and the
        # unblock below, so whatever lands, no signal is left blocked.
        try:
            while todo:
                try:
                    signal.signal(*todo[0])
                    del todo[0]
                except BaseException as exc:  # (as above) a third at once can still leave one unset
                    error = error or exc
        finally:
            try:
                if blocked is not None:
                    signal.pthread_sigmask(
                        signal.SIG_UNBLOCK, taken - blocked
                    )  # a pending stop: the caller's handler, now
            finally:
                if error is not None:
                    raise error


def _give_back_unmasked(found: dict) -> None:
    """:func:`_give_back` where no signal can be blocked (Windows: no ``pthread_sigmask``). Every
    signal first goes to a handler that only notes it, then each to the caller's; a stop noted
    meanwhile is raised (``signal.raise_signal``) once all are back, to the caller's handler,
    whose own rules apply. So a stop goes to the command's handler only as the notes are set,
    one call per signal, before any work -- on Windows, SIGINT and SIGTERM: two calls -- never
    to a command that has finished its give-back; and one the caller's handler raises for (a
    Ctrl-C to a handler back already) is carried past the rest and raised after them, as
    :func:`_give_back` does. A stop landing in the raise's own moment is the caller's, in place."""
    came: list[int] = []

    def note(signum, frame):
        came.append(signum)

    todo = [(sig, note) for sig in found] + list(found.items())
    error: BaseException | None = None
    try:
        while todo:
            try:
                while todo:
                    signal.signal(*todo[0])  # set again if a raise lands after it: the same handler
                    del todo[0]
            except BaseException as exc:  # a caller's handler back already ran and raised: carry on
                error = error or exc
    finally:
        # (a raise at the loop's jump back, outside the try above: the handlers left are put back here)
        try:
            while todo:
                try:
                    signal.signal(*todo[0])
                    del todo[0]
                except BaseException as exc:
                    error = error or exc
        finally:
            try:
                for signum in dict.fromkeys(came):  # each stop once, in the order they came
                    try:
                        signal.raise_signal(signum)
                    except BaseException as exc:
                        # a caller's handler that raises (Python's Ctrl-C) cut the loop short: the
                        # stops noted after it were lost (review s54rv). Carried to the end instead
                        error = error or exc
            finally:
                if error is not None:
                    raise error


def _on_main_thread() -> bool:
    import threading

    return threading.current_thread() is threading.main_thread()


def _check_environment() -> None:
    """The environment's settings read once, before any work: a bad one was reported as a
    problem of the first file that needed it ("exp.h5: cannot be read as hdf5: RADIOKIT_MEMORY_
    BUDGET='abc' ...", or "exp.h5: frame 20: RADIOKIT_THREADS=..." after the calibration)."""
    from radiokit._threads import threads
    from radiokit.io._budget import memory_budget

    threads()
    memory_budget()


def _writable_folder(folder: Path) -> bool:
    """Whether ``folder`` is, or could be made as, a folder this user writes into: it or its
    nearest existing parent is a folder with write access (as matplotlib will try)."""
    for path in (folder, *folder.parents):
        if os.path.lexists(path):
            return path.is_dir() and os.access(path, os.W_OK | os.X_OK)
    return False


def _quiet_matplotlib() -> None:
    """Give matplotlib a temporary folder (``MPLCONFIGDIR``, removed at exit) when it cannot make
    its own under the home folder or ``XDG_*``, and only then: a user without a home folder (a
    service account's /nonexistent, a read-only container) got two lines of matplotlib's about
    it on every command that draws. Before matplotlib is imported: it reads them once."""
    if os.environ.get("MPLCONFIGDIR") or "matplotlib" in sys.modules:
        return
    try:
        home = Path.home()
    except (RuntimeError, KeyError):  # no HOME and no entry in the password database
        home = None
    folders = [os.environ.get(xdg) or (home and home / default) for xdg, default in _XDG]
    if all(f and _writable_folder(Path(f) / "matplotlib") for f in folders):
        return
    import atexit
    import shutil
    import tempfile

    folder = tempfile.mkdtemp(prefix="radiokit-matplotlib-")
    atexit.register(shutil.rmtree, folder, ignore_errors=True)
    os.environ["MPLCONFIGDIR"] = folder


#: where matplotlib keeps its configuration and its font cache (Linux), beside the variables naming them
_XDG = (("XDG_CONFIG_HOME", ".config"), ("XDG_CACHE_HOME", ".cache"))


def _one_warning_per_file() -> None:
    """A warning about a file (it carries ``path``) shown once per command: `radiokit correct
    exp.h5` opens the file to calibrate and again to correct, and each open warned (with the peak
    of the frames each read first, so the two lines differed and Python's filter kept both)."""
    shown = set()
    # a fresh set per command: main() run again in one process (tests) wraps the original anew
    show = getattr(warnings.showwarning, "original", warnings.showwarning)

    def once(message, category, *rest, **kw):
        key = (category, getattr(message, "path", None))
        if key[1] is not None:
            if key in shown:
                return
            shown.add(key)
        show(message, category, *rest, **kw)

    once.original = show
    warnings.showwarning = once


def _take_signals(command: str, signals) -> None:
    """The command line's handler (:func:`_terminated`) for the stop ``signals``. Ctrl-C's in
    place of Python's own, which raised inside an import; one the command was started ignoring
    stays ignored (`cmd &` in a script ignores Ctrl-C; `nohup cmd` a hang-up, so that it outlives
    the terminal: taken, closing the terminal stopped it). ``acquire`` owns the others (the tube
    goes off first, by its guard's; before the guard, nothing is sent or written), but takes
    Ctrl-C's too: raised before its guard, inside h5py's imports, it was swallowed and the series
    went on."""
    for sig in signals:
        if signal.getsignal(sig) is signal.SIG_IGN:
            take = False
        elif sig == signal.SIGINT:
            take = signal.getsignal(sig) is signal.default_int_handler
        else:
            take = command != "acquire"  # the demo's runs take them over
        if take:
            signal.signal(sig, _terminated)


def _main(argv) -> int:
    try:
        # a command's own module (acquire's: the X-ray driver) is imported as the parser is built:
        # a stop here is one line too, nothing opened yet (the command's handlers come later);
        # so is one while this first import runs (a traceback and death by SIGINT, before)
        from radiokit.interrupts import STOP_SIGNALS, exit_status, forget_stops_after_the_end, lost_stops_redelivered

        forget_stops_after_the_end()  # a command of its own (main() may run several in one process)
        parser = build_parser()
        args = parser.parse_args(argv)
    except KeyboardInterrupt as exc:
        print("radiokit: interrupted while starting: nothing was read, sent or written", file=sys.stderr)
        return 128 + int(getattr(exc, "signum", signal.SIGINT))  # Python's own Ctrl-C, unless a caller's handler
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    # `radiokit sim run`, named whole as argparse's own errors and --help name it (not "radiokit sim")
    name = " ".join(filter(None, (args.command, getattr(args, "sim_command", None))))
    given = _given_names(args)
    if not _debug(args):  # tifffile logs what it tolerates; the one line below says what matters
        logging.getLogger("tifffile").setLevel(logging.CRITICAL)
        # a warning is for the user: the command's line, not radiokit's file, line and source
        warnings.formatwarning = lambda message, category, *_, **__: (
            f"radiokit {name}: {category.__name__}: {_one_line(str(message), given)}\n"
        )
    _one_warning_per_file()
    _quiet_matplotlib()
    _take_signals(args.command, STOP_SIGNALS)
    try:
        if args.command != "acquire":  # never in the way of a switch-off (acquire source off)
            _check_environment()
        with lost_stops_redelivered():  # acquire's own guard takes over while it runs
            return int(args.func(args) or 0)
    except KeyboardInterrupt as exc:
        print(f"radiokit {name}: interrupted; no partial output was left", file=sys.stderr)
        return exit_status(exc)
    except Exception as exc:
        if isinstance(exc, BrokenPipeError) and _stdout_gone():
            # the reader of the output went away (`radiokit info *.img | head -1`): not an error of
            # the command's ("[Errno 32] Broken pipe" after calibrate had written its file); quiet,
            # with the status a shell gives a command that SIGPIPE ended
            return 128 + signal.SIGPIPE
        if not _user_error(exc) or _debug(args):
            raise
        if _interrupted(exc) is not None:  # a C extension turned the interrupt into its own error
            print(f"radiokit {name}: interrupted; no partial output was left", file=sys.stderr)
            return exit_status(_interrupted(exc))
        for one in getattr(exc, "errors", None) or [exc]:  # InputErrors: each bad input on its own line
            print(_error_line(name, one, given), file=sys.stderr)
        return 2


def _given_names(args) -> list[str]:
    """The files named on the command line (every path option and argument), as given."""
    names = []
    for value in vars(args).values():
        names += [str(v) for v in (value if isinstance(value, (list, tuple)) else [value]) if isinstance(v, Path)]
    return names


def _names_shown(text: str, names) -> str:
    """``text`` with each of ``names`` that holds a control character (a newline, an escape) as
    :func:`radiokit._names.shown` prints it, wherever a message put it raw. Why: a message names a
    file however its writer chose, and the one line folds a raw newline into a space, ``a b.tif``,
    naming no file (s51); the command line's own messages use ``shown``, and this holds the rule
    for every other line a command prints of its files (the library's errors and warnings).
    Longest first: a name inside a longer one is not split; a name the message already printed
    as names print is left so (a name's backslash is in its quoted form too: ``'x\\\\'`` holds
    ``x\\``, and a second pass quoted it again, s52)."""
    import re

    quoted = {n: shown(n) for n in names if shown(n) != n}
    if not quoted:
        return text
    forms = {form: form for form in quoted.values()} | quoted  # at one place, a quoted form comes first
    pattern = "|".join(re.escape(f) for f in sorted(forms, key=len, reverse=True))
    return re.sub(pattern, lambda m: forms[m.group(0)], text)


def _one_line(text: str, names=()) -> str:
    """``text`` as one printed line: the files given (``names``) as names print
    (:func:`_names_shown`), any other control character escaped (a file's own text: a dataset's
    name, review s51rv2), its whitespace folded."""
    return " ".join(controls_escaped(_names_shown(text, names)).split())


def _error_line(command: str, exc: BaseException, names=()) -> str:
    """A user's error as the one line every command prints: ``radiokit COMMAND: MESSAGE``, the
    files given (``names``: :func:`_given_names`) as names print."""
    message = _names_shown(str(exc) or type(exc).__name__, names)
    # the API's words name its keyword too; at the shell only the option means anything
    from radiokit.io import OutputExistsError

    message = message.replace(OutputExistsError.HOW, "--overwrite")
    if isinstance(exc, MemoryError):
        message = f"out of memory ({message}); lower RADIOKIT_MEMORY_BUDGET or read fewer frames"
    return f"radiokit {command}: {_one_line(message)}"


if __name__ == "__main__":
    # `python -m radiokit.cli` ends as the command returns, as the console script does: script(),
    # not main(), whose handlers given back let a Ctrl-C after a finished acquire end it by SIGINT
    sys.exit(script())
