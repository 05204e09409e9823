"""The HTML report: it renders, its images load, its numbers and sentences are the ones given."""

import dataclasses
import re
import subprocess
import sys
from html.parser import HTMLParser
from pathlib import Path

import numpy as np
import pytest
from matplotlib import image as mpimg

from radiokit import report as R
from radiokit.enhance import Domain, to_domain
from radiokit.report import MAX_PNG_BYTES, stiffness_share, write_report
from radiokit.results import Bound, DomainMeasures, Enhancement, Images, KMeasure, PairResult, Results, Rois

SOURCE = "/data/run<1>&co/exp.h5"


def _domain(dom, c_ref, cnr_ref, weber_ref, per_k):
    """DomainMeasures from ``{k: (contrast, cnr, weber, improvement factor)}``."""
    return DomainMeasures(
        Domain(dom), c_ref, cnr_ref, weber_ref, tuple(KMeasure(float(k), *v) for k, v in per_k.items())
    )


def _record(ks, factors, *, truth, scene="block <stiff> & soft", control=None):
    q = {
        "ok": True,
        "reason": "",
        "rc_before": 12.5,
        "rc_after": 3.25,
        "ncc_before": 0.9,
        "ncc_after": 0.998,
        "folds": 0,
        "min_det_j": 0.97,
        "seconds": 1.5,
        "iterations": 40,
    }
    epe = {"epe_median": 0.071, "epe_p95": 0.183} if truth else None
    cr = {"2->3": (0.743, 0.812), "1->3": (0.751, 0.8), "1->2": (0.76, 0.81)}
    quality = {
        "2->3": q,
        "1->3": {**q, "ok": False, "reason": "folding: 3 pixels with det J <= 0", "folds": 3},
        "1->2": {**q, "note": "stopped at 60 iterations; not flagged for it <slow>"},
    }
    pairs = tuple(
        PairResult(int(n[0]), int(n[-1]), "rc", quality[n], {Domain.LOG: v[0], Domain.NEGATIVE: v[1]}, None, None, epe)
        for n, v in cr.items()
    )
    domains = {
        Domain.LOG: _domain(
            "log", 0.2512, 25.1, 0.27, {k: (0.2512 * f, 20.0 * f, 0.27 * f, f) for k, f in factors.items()}
        ),
        Domain.NEGATIVE: _domain(
            "negative", 0.0915, 9.2, 0.2, {k: (0.0915 * 1.2, 9.0, 0.24, 1 + 0.2 * float(k)) for k in ks}
        ),
    }
    return Results(
        SOURCE,
        scene,
        truth,
        0.05,
        Domain.LOG,
        tuple(float(k) for k in ks),
        "rc",
        (1, 2, 3),
        (0.15, 0.20, 0.25),
        Rois((100, 164, 200, 264), (28, 36, 28, 36), (28, 36, 4, 12)),
        domains,
        pairs,
        "2->3",
        32,
        Bound(None, ""),
        {"improvement_factor": {"1": 1.4, "2": 2.0}, "change_ratio": [0.66, 0.84]},
        {
            "calibrate_s": 0.5,
            "correct_s": 1.25,
            "register_s": 12.0,
            "enhance_s": 0.01,
            "measure_s": 0.02,
            "total_s": 14.37,
        },
        control,
    )


def _control(ks):
    """A control run: the inclusion as soft as the background."""
    cf = {"1": 1.113, "2": 1.226}
    ctrl = _record(ks, {k: cf.get(k, 1.1) for k in ks}, truth=False)
    neg = _domain("negative", 0.09, 9.0, 0.2, {k: (0.1, 9.0, 0.2, 1.09 * float(k)) for k in ks})
    log = _domain("log", 0.2491, 25.0, 0.27, {k: (0.25, 20.0, 0.27, cf.get(k, 1.1)) for k in ks})
    pairs = tuple(
        dataclasses.replace(p, change_ratio={Domain.LOG: 0.95, Domain.NEGATIVE: 0.97})
        for p in ctrl.pairs
        if p.name == "2->3"
    )
    return dataclasses.replace(ctrl, domains={Domain.LOG: log, Domain.NEGATIVE: neg}, pairs=pairs)


def _synthetic(n=64, *, control=False, truth=False, ks=("1", "2"), noise=0.01, seed=0):
    """Three steps of a body with a denser blob that thins less than the background."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:n, 0:n].astype(np.float32)
    blob = np.exp(-((yy - n / 2) ** 2 + (xx - n / 2) ** 2) / (2 * (n / 10) ** 2)).astype(np.float32)
    ramp = 0.1 * xx / n

    def step(thickness, incl):
        img = thickness * (1.0 + ramp) + incl * blob
        return (img + noise * rng.standard_normal((n, n))).astype(np.float32)

    steps = np.stack([step(1.00, 0.30), step(0.95, 0.29), step(0.90, 0.28)])
    ref, moving = steps[-1], steps[-2]
    registered = moving.copy()
    d = np.stack([0.5 * np.sin(xx / n * np.pi), 0.3 * np.cos(yy / n * np.pi)]).astype(np.float32)
    det_j = (1 + 0.01 * np.sin(xx / 7) * np.cos(yy / 5)).astype(np.float32)
    enhanced = {}
    for dom in (Domain.LOG, Domain.NEGATIVE):
        r, g = to_domain(ref, dom), to_domain(registered, dom)
        D = r - g
        enhanced[dom] = Enhancement(
            dom, r, g, D, tuple((float(k), (r + float(k) * (D - D.mean())).astype(np.float32)) for k in ks)
        )
    tf = d + np.float32(0.05) if truth else None
    images = Images(
        steps,
        ref,
        registered,
        np.roll(moving, 1, axis=1),
        d,
        det_j,
        None,
        enhanced,
        {},
        tf,
        np.hypot(*(d - tf)) if truth else None,
    )
    factors = {"1": 1.374, "2": 2.046, "0.5": 1.187, "3": 3.1}
    factors = {k: factors[k] for k in ks}
    results = _record(ks, factors, truth=truth, control=_control(ks) if control else None)
    return results, images


class _Parser(HTMLParser):
    def __init__(self):
        super().__init__()
        self.imgs, self.tags, self.text = [], [], []

    def handle_starttag(self, tag, attrs):
        self.tags.append(tag)
        if tag == "img":
            self.imgs.append(dict(attrs)["src"])

    def handle_data(self, data):
        if self.lasttag not in ("style", "title"):  # what a reader sees on the page
            self.text.append(data)


def _parse(path):
    p = _Parser()
    raw = Path(path).read_text(encoding="utf-8")
    p.feed(raw)
    return raw, p, " ".join(" ".join(p.text).split())


@pytest.fixture(scope="module")
def full_report(tmp_path_factory):
    out = tmp_path_factory.mktemp("full")
    results, arrays = _synthetic(control=True, truth=True, ks=("0.5", "1", "2", "3"))
    return write_report(out, results, arrays), results


@pytest.fixture(scope="module")
def bare_report(tmp_path_factory):
    out = tmp_path_factory.mktemp("bare")
    results, images = _synthetic()
    # and numerics that break naive code: a masked-out band (NaN), a constant difference image
    neg = images.enhanced[Domain.NEGATIVE]
    images.enhanced[Domain.NEGATIVE] = dataclasses.replace(neg, difference=np.zeros((64, 64), np.float32))
    for img in (images.steps[0], images.enhanced[Domain.LOG].reference, images.enhanced[Domain.LOG].images[0][1]):
        img[30:34] = np.nan
    main = dataclasses.replace(results.pair("2->3"), quality={"ok": False, "reason": "diverged <badly>"})
    results = dataclasses.replace(
        results,
        pairs=tuple(main if p.name == "2->3" else p for p in results.pairs),
        scene='[scene]\nname = "block"\nnote = "E_inclusion > E_background & dense"\n',
    )
    return write_report(out, results, images), results  # RuntimeWarnings are errors here


def _check_images(html_path, expected_min):
    _, parser, _ = _parse(html_path)
    assert len(parser.imgs) >= expected_min
    for src in parser.imgs:
        assert not src.startswith(("/", "http:", "https:", "data:"))
        f = html_path.parent / src
        assert f.is_file(), src
        assert f.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n", src
        assert f.stat().st_size < MAX_PNG_BYTES, src
        img = mpimg.imread(f)
        assert img.shape[0] >= 150 and img.shape[1] >= 250, (src, img.shape)
        assert float(np.std(img)) > 0.02, src
    return parser.imgs


def test_html_written_and_every_image_loads(full_report):
    path, _ = full_report
    assert path == path.parent / "report.html" and path.is_file()
    srcs = _check_images(path, 5)
    assert {Path(s).name for s in srcs} == {
        "projections.png",
        "profiles.png",
        "difference.png",
        "rois.png",
        "registration.png",
    }


def test_page_is_self_contained(full_report):
    raw, parser, _ = _parse(full_report[0])
    assert "script" not in parser.tags and "link" not in parser.tags
    assert "<script" not in raw.lower()
    assert not re.search(r"(src|href)\s*=\s*\"(https?:)?//", raw)
    assert "<style>" in raw


def test_headline_numbers_appear_formatted(full_report):
    _, _, text = _parse(full_report[0])
    for s in ("1.37", "2.05", "0.74", "0.2512", "0.66\u20130.84", "12.00 s", "0.071 / 0.183"):
        assert s in text, s
    # the record's total (14.37 s) was taken before the report: the page adds the report's time
    report_s = float(re.search(r"\breport (\d+\.\d\d) s", text).group(1))
    total_s = float(re.search(r"total processing time (\d+\.\d\d) s", text).group(1))
    assert total_s == pytest.approx(14.37 + report_s, abs=0.01)
    assert "1.374" not in text  # the improvement factors are shown to 2 decimals
    summary = text.split("What the numbers show.")[1]
    assert "1.37 at k=1" in summary and "2.05 at k=2" in summary and "0.74 times" in summary
    # the text speaks of k = 1 (the paper's direct addition) even when a smaller k comes first
    assert "contrast-to-noise ratio changes by a factor of 1.09 at k=1" in summary
    assert (
        "improves the contrast by 1.11 at k=1: the share of the gain that needs the inclusion's "
        "stiffness is 70 %" in summary
    )


def test_text_is_escaped(full_report):
    raw, _, text = _parse(full_report[0])
    assert "/data/run&lt;1&gt;&amp;co/exp.h5" in raw
    assert SOURCE not in raw and "<stiff>" not in raw and "<1>" not in raw
    assert SOURCE in text and "block <stiff> & soft" in text  # and it reads back as written
    assert "folding: 3 pixels with det J &lt;= 0" in raw
    assert "note: stopped at 60 iterations; not flagged for it &lt;slow&gt;" in raw  # a trusted result's note


def _sentences(text):
    pat = (
        r"In the (log|negative) domain, the control's improvement at k=1 is ([\d.]+) vs ([\d.]+): "
        r"(-?\d+) % of the compression-induced contrast"
    )
    return {m[0]: (float(m[1]), float(m[2]), int(m[3])) for m in re.findall(pat, text)}


def test_control_sentence_percentage_is_the_formula(full_report):
    path, results = full_report
    _, _, text = _parse(path)
    assert "Stiff inclusion vs control (inclusion as soft as the background)" in text
    found = _sentences(text)
    assert set(found) == {"log", "negative"}
    for dom, (ctrl, stiff, pct) in found.items():
        if_s = results.domains[Domain(dom)].at(1).improvement_factor
        if_c = results.control.domains[Domain(dom)].at(1).improvement_factor
        assert (ctrl, stiff) == (round(if_c, 2), round(if_s, 2))
        assert pct == round(100 * (if_s - if_c) / (if_s - 1))
    assert found["log"][2] == 70  # (1.374 - 1.113) / 0.374 = 0.698
    negative = text.split("In the negative domain, the control's")[1]
    assert "exponential in the line integral" in negative


def test_no_control_no_truth_still_renders(bare_report):
    path, _ = bare_report
    _, _, text = _parse(path)
    assert "as soft as the background" not in text and "control" not in text.lower()
    assert "end-point error" not in text and "EPE" not in text
    _check_images(path, 5)
    assert "1.37" in text and "Timings" in text
    assert "Caution: the registration of 2->3 was flagged (diverged <badly>)" in text
    raw = path.read_text(encoding="utf-8")  # a simulation's TOML scene is folded away, escaped
    assert re.search(
        r"<details><summary>scene configuration</summary><pre>\[scene\]\nname = &quot;block&quot;"
        r"\nnote = &quot;E_inclusion &gt; E_background &amp; dense&quot;",
        raw,
    )


def test_only_the_typed_records_are_taken(tmp_path):
    results, images = _synthetic()
    with pytest.raises(TypeError, match="write_report takes radiokit.results.Results and Images"):
        write_report(tmp_path / "new", results.to_json(), images)


def test_every_k_is_reported(full_report):
    _, _, text = _parse(full_report[0])
    for k in ("k=0.5", "k=1", "k=2", "k=3"):
        assert f"enhanced, {k}" in text and f"improvement factor, {k}" in text
    assert "3.10" in text and "1.19" in text


def test_noisy_figures_are_kept_under_the_size_limit(tmp_path):
    """Noise compresses badly: the PNG is palette-quantised, then drawn smaller, until it fits."""
    rng = np.random.default_rng(0)
    fig, axes, _ = R._grid_figure(1, 2, (3.8, 3.6), R._Cell())
    for ax in axes.ravel():
        ax.imshow(rng.standard_normal((300, 300)), cmap="viridis")
    R._save(fig, tmp_path / "noise.png", max_bytes=60_000)
    data = (tmp_path / "noise.png").read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) <= 60_000
    img = mpimg.imread(tmp_path / "noise.png")
    assert img.shape[1] >= 200 and float(np.std(img)) > 0.05


@pytest.mark.parametrize(
    "domain, if_stiff, if_control, expected",
    [
        (
            "log",
            1.4,
            1.1,
            "75 % of the compression-induced contrast needs the inclusion's stiffness; the rest "
            "comes from attenuation alone",
        ),
        ("log", 1.004, 1.1, "is not measurable"),
        (
            "log",
            1.4,
            0.9,
            "125 % of the compression-induced contrast needs the inclusion's stiffness; "
            "attenuation alone (the thinning of a denser inclusion) would lower the contrast",
        ),
        (
            "log",
            1.2,
            1.3,
            "-50 % of the compression-induced contrast needs the inclusion's stiffness: the control gains more",
        ),
        ("negative", 1.4, 1.1, "exponential in the line integral"),
        ("log", None, 1.1, "not measurable"),
    ],
)
def test_control_sentence_wording(domain, if_stiff, if_control, expected):
    sentence = R._control_sentence(domain, 1.0, if_stiff, if_control)
    assert sentence.startswith(f"In the {domain} domain, the control's improvement at k=1 is ")
    assert expected in sentence
    assert ("exponential" in sentence) == (domain == "negative")


@pytest.mark.parametrize(
    "if_stiff, if_control, expected",
    [
        (1.4, 1.1, 0.75),
        (2.0, 1.0, 1.0),
        (2.0, 0.5, 1.5),
        (1.2, 1.3, -0.5),
        (1.4, 1.4, 0.0),
        (1.0, 1.2, None),
        (1.005, 1.0, None),
        (0.995, 1.0, None),
        (float("nan"), 1.1, None),
        (1.4, None, None),
        ("1.4", "1.1", 0.75),
    ],
)
def test_stiffness_share(if_stiff, if_control, expected):
    got = stiffness_share(if_stiff, if_control)
    assert got == pytest.approx(expected) if expected is not None else got is None


def test_report_imports_neither_sim_nor_acquisition():
    code = (
        "import sys, radiokit.report; "
        "bad = sorted(m for m in sys.modules if m.split('.')[0] in ('sim', 'acquisition')); "
        "assert not bad, bad"
    )
    subprocess.run([sys.executable, "-c", code], check=True)


def test_the_total_time_includes_the_report_it_times(tmp_path):
    """A record whose total was taken before its report (as ``process`` takes it): the page's
    total, in the headline and the timings table alike, is that total plus the report's own
    time, so no row exceeds it and it matches results.json's. It showed the total from before
    the report, below the sum of its own rows."""
    results, images = _synthetic()
    results = dataclasses.replace(results, timings={"register_s": 1.0, "total_s": 2.0})
    _, _, text = _parse(write_report(tmp_path, results, images))
    report_s = float(re.search(r"\breport (\d+\.\d\d) s", text).group(1))
    total_s = float(re.search(r"\btotal (\d+\.\d\d) s", text).group(1))
    headline_s = float(re.search(r"total processing time (\d+\.\d\d) s", text).group(1))
    assert headline_s == total_s
    assert total_s == pytest.approx(2.0 + report_s, abs=0.01)  # each shown to 0.005
    assert report_s > 0.01  # the figures take time: the old total (2.00) is told apart


def test_the_stated_definitions_reproduce_the_table(tmp_path):
    """The page's words for CNR and Weber give its numbers: on a negative-domain image whose
    ROIs hold known values, the Weber contrast is the contrast over the background mean's
    magnitude (the page said "over the background mean", which gives the opposite sign there)
    and the CNR the contrast over the population standard deviation."""
    from radiokit.measure import ROI, cnr, weber

    img = np.full((8, 8), -0.5)
    img[:2, :2] = -0.3  # inclusion: more attenuation, brighter (less negative)
    img[4:6, 4:6] = [[-0.6, -0.4], [-0.6, -0.4]]  # background: mean -0.5, population std 0.1
    inc, bg = ROI(0, 2, 0, 2), ROI(4, 6, 4, 6)
    assert weber(img, inc, bg) == pytest.approx(0.2 / abs(-0.5))
    assert cnr(img, inc, bg) == pytest.approx(0.2 / 0.1)
    results, images = _synthetic()
    _, _, text = _parse(write_report(tmp_path, results, images))
    assert "Weber: contrast over |mean of the background ROI|" in text
    assert "CNR: contrast over the background ROI's (population) standard deviation" in text


def test_a_trusted_registration_that_did_not_converge_is_not_called_converged():
    """A pair its checks trust though its finest level was still moving when the budget ended
    (``converged`` False, the reason in ``note``) was described as having passed "(similarity
    improved, no folding, converged)"; the sentence now gives the note instead."""
    results = _record(("1", "2"), {"1": 1.1, "2": 1.2}, truth=False)
    note = "stopped at 60 iterations; not flagged for it: the residual moves 0.12 px (slow, not lost)"
    main = results.pair("2->3")
    slow = dataclasses.replace(main, quality={**main.quality, "converged": False, "note": note})
    results = dataclasses.replace(results, pairs=tuple(slow if p is main else p for p in results.pairs))
    text = " ".join(R._pair_sentences(results, R.PAPER))
    assert "passed its checks" in text and "converged)" not in text
    assert note in text
    # a converged one keeps the word
    assert "converged)" in " ".join(R._pair_sentences(_record(("1", "2"), {"1": 1.1, "2": 1.2}, truth=False), R.PAPER))


@pytest.mark.parametrize(
    "x, text", [(126.4, "126"), (1264.0, "1.26e+03"), (10.0, "10.0"), (3.1, "3.10"), (0.001234, "0.00123")]
)
def test_cnrs_keep_three_significant_digits_without_a_bare_point(x, text):
    """'#.3g' kept "10.0" beside "16.6" but wrote a CNR of 126 as "126." (review s34-r3)."""
    from radiokit.results import sig3

    assert sig3(x) == text


def test_the_report_gives_autos_reason_for_its_preset(tmp_path, bare_report):
    """Found by a new user: the report named the preset auto chose, not why (only results.json
    had ``preset_reason``). One line below the registration table gives it, escaped."""
    results, images = _synthetic()
    reason = "weak texture: interior texture/noise 0.80 >= 0.5 <x>"
    main = results.pair("2->3")
    chosen = dataclasses.replace(main, quality={**main.quality, "preset": "weak", "preset_reason": reason})
    results = dataclasses.replace(results, pairs=tuple(chosen if p is main else p for p in results.pairs))
    raw, _, text = _parse(write_report(tmp_path, results, images))
    assert f"Preset auto chose, per pair: {R._pair_label('2->3')}: weak ({reason})." in text, text
    assert "<x>" not in raw
    # a pair without auto's record (a preset given, a peer method): no line. The module's report of
    # the same pairs, none with that record (a report of its own here cost 3-7 s; session 42)
    path, plain = bare_report
    assert not any(p.quality.get("preset") or p.quality.get("preset_reason") for p in plain.pairs)
    assert "Preset auto chose" not in _parse(path)[2]


def test_results_json_reads_back_byte_for_byte_with_k_keyed_by_number(tmp_path):
    """Review s43: results.json keys k by text (JSON must), and the records kept the paper's
    improvement factors keyed "1" beside ``improvement_factor`` keyed 1.0: ``record.paper[...][1.0]``
    was a KeyError. In memory every k is a number; the file is unchanged."""
    import json

    from radiokit.results import load_results

    ks = ("1", "2")
    record = _record(ks, {"1": 1.1, "2": 1.2}, truth=True, control=_control(ks))
    text = record.write_json(tmp_path / "results.json").read_text()
    back = load_results(tmp_path / "results.json")
    assert back.write_json(tmp_path / "again.json").read_text() == text
    assert json.loads(text)["paper"] == {"improvement_factor": {"1": 1.4, "2": 2.0}, "change_ratio": [0.66, 0.84]}
    for rec in (record, back, back.control):
        assert rec.paper["improvement_factor"] == {1.0: 1.4, 2.0: 2.0}
        assert set(rec.paper["improvement_factor"]) == set(rec.improvement_factor) == {1.0, 2.0}
    assert R.PAPER["improvement_factor"] == {1.0: 1.4, 2.0: 2.0}


def test_a_pairs_quality_is_typed_and_still_reads_as_the_dict_it_was(tmp_path):
    """Review s43: ``PairResult.quality`` was a plain dict where every other result is a typed
    record. It is a read-only :class:`radiokit.results.PairQuality`: register.Quality's fields and
    the run's choices as attributes (None where the file records none), and the mapping of the
    recorded keys, in the file's order, that existing code reads (``quality["ok"]``)."""
    import copy
    import dataclasses as dc
    import pickle

    from radiokit.register import Quality
    from radiokit.results import PairQuality, load_results

    _record(("1",), {"1": 1.1}, truth=False).write_json(tmp_path / "results.json")
    for pair in load_results(tmp_path / "results.json").pairs:
        q = pair.quality
        assert isinstance(q, PairQuality)
        assert q.ok is q["ok"] is pair.ok and q.reason == q["reason"] == pair.reason
        assert q.rc_after == q["rc_after"] == 3.25 and q.iterations == 40
        assert q.body_scale is None and "body_scale" not in q  # not recorded: None, as in the file's null
        assert q.get("preset") is None and q.preset is None
        assert list(q) == list(dict(q)) and dict(q) == q and len(q) == len(dict(q))
        assert pickle.loads(pickle.dumps(q)) == q == copy.deepcopy(q)
        with pytest.raises(AttributeError):
            q.ok = False
        with pytest.raises(TypeError):
            q["ok"] = False
        with pytest.raises(AttributeError, match="no_such"):
            q.no_such  # noqa: B018 (the lookup is the point)
    # every field of register.Quality is an attribute (typed in the class), so the two cannot drift
    assert {f.name for f in dc.fields(Quality)} <= set(PairQuality.__annotations__)
    notes = load_results(tmp_path / "results.json").pair("1->2").quality
    assert notes.note == "stopped at 60 iterations; not flagged for it <slow>"


def test_a_pairs_quality_still_serialises_and_copies_as_the_dict_it_was(tmp_path):
    """Review s43rr: when ``PairResult.quality`` became a read-only Mapping, code written for the
    dict it was broke: ``json.dumps(pair.quality)`` raised TypeError ("not JSON serializable"),
    as did ``quality.copy()`` and ``quality | {...}``. It is a dict again, still read-only."""
    import json

    from radiokit._json import strict
    from radiokit.results import load_results

    _record(("1",), {"1": 1.1}, truth=False).write_json(tmp_path / "results.json")
    q = load_results(tmp_path / "results.json").pair("1->2").quality
    plain = dict(q)
    assert json.loads(json.dumps(q)) == json.loads(json.dumps(plain)) == strict(q)
    mine = q.copy()
    mine["ok"] = False  # a copy is the caller's own, as a dict's copy was
    assert q["ok"] is True and (q | {"ok": False})["ok"] is False and dict(q) == plain
    for change in (
        lambda: q.update(ok=False),
        lambda: q.pop("ok"),
        lambda: q.setdefault("new", 1),
        lambda: q.clear(),
        lambda: q.popitem(),
        lambda: q.__delitem__("ok"),
        lambda: q.__ior__({"ok": False}),
    ):
        with pytest.raises(TypeError, match="read-only"):
            change()
    assert dict(q) == plain


def test_large_images_are_drawn_strided_over_the_whole_field():
    """A panel shows every step-th pixel, as many as it has dots or more, over the full extent."""
    fig, axes, _ = R._grid_figure(1, 1, (2.0, 2.0), R._Cell(0, 0, 0, 0))
    ax = axes[0, 0]  # the whole figure: 200 x 200 dots at 100 dpi
    img = np.arange(1000 * 900, dtype=np.float64).reshape(1000, 900)
    im = R._imshow(ax, img, cmap="gray")
    shown = im.get_array()
    step = 900 // 200  # the largest stride keeping >= 200 columns and rows
    np.testing.assert_array_equal(shown, img[::step, ::step])
    assert min(shown.shape) >= 200
    assert im.get_extent() == [-0.5, 899.5, 999.5, -0.5]  # the field of view, not the strided one
    small = R._imshow(ax, img[:50, :60])
    np.testing.assert_array_equal(small.get_array(), img[:50, :60])
