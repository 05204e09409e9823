"""The README's self-contained examples run as written."""

import re
from pathlib import Path

import numpy as np

README = Path(__file__).resolve().parents[1] / "README.md"


def _block(heading):
    text = README.read_text()
    section = text[text.index(heading) :]
    return re.search(r"```python\n(.*?)```", section, re.S).group(1)


def test_calibrate_and_correct_example(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    ns = {}
    exec(compile(_block("### Calibrate and correct"), "README.md", "exec"), ns)
    import numpy as np

    # 1550 counts with dark 100 and flat 3000: I/I0 = 0.5
    assert abs(float(np.median(ns["mu_l"])) - np.log(2)) < 0.01
    assert abs(float(np.median(ns["t"])) - 0.5) < 0.005
    assert (tmp_path / "cal.h5").exists()


def test_simulation_example():
    ns = {}
    exec(compile(_block("### Simulate the experiment"), "README.md", "exec"), ns)
    from sim.mechanics import uniaxial_block_force

    force, _ = uniaxial_block_force(0.25, 5, 0.495, 100.0)
    assert abs(ns["s25"].plate_force_n / force - 1) < 1e-6
    assert ns["line_integral"].shape == (560, 560) and ns["d"].shape == (2, 560, 560)


def test_register_example():
    ns = {}
    exec(compile(_block("### Register"), "README.md", "exec"), ns)
    reg = ns["reg"]
    assert reg.quality.ok
    inner = (slice(20, -20), slice(20, -20))
    assert np.abs(reg.displacement[(slice(None),) + inner] - 1.5).max() < 0.1


def test_acquire_example(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    ns = {}
    exec(compile(_block("### Acquire"), "README.md", "exec"), ns)
    from radiokit.io import ImageKey, read

    f = read(ns["result"].output)
    assert ns["result"].frames_written == 10 == f.data.shape[0]
    keys = f.meta["image_key"]
    assert (keys == ImageKey.PROJECTION).sum() == 6 and (keys == ImageKey.DARK).sum() == 2


def test_the_acquire_examples_run_in_order_in_one_folder(tmp_path, monkeypatch):
    """A reader following "Acquire" in one folder ran the Python example, then the protocol.toml's
    `--dry-run`, which refused: both wrote series.h5, and an existing experiment file is refused by
    the dry run as by the run (raw data is never overwritten). The two name different files."""
    from conftest import run_cli

    monkeypatch.chdir(tmp_path)
    text = README.read_text()
    python_output = re.search(r'"output": "([^"]+)"', _block("### Acquire")).group(1)
    toml = next(b for b in re.findall(r"```toml\n(.*?)```", text, re.S) if b.startswith("# protocol.toml"))
    toml_output = re.search(r'^output = "([^"]+)"', toml, re.M).group(1)
    assert python_output != toml_output, "the Python example and protocol.toml write the same file"
    (tmp_path / python_output).write_bytes(b"")  # the example's file, there before the dry run
    (tmp_path / "protocol.toml").write_text(toml)
    res = run_cli("acquire", "protocol.toml", "--dry-run", cwd=tmp_path)
    assert res.returncode == 0, res.stderr


def test_weak_alpha_example(capsys):
    """The noise the example adds (0.01 in both images) is what ``weak`` reads and sets alpha by."""
    ns = {}
    exec(compile(_block("`weak`'s alpha follows the pair's noise"), "README.md", "exec"), ns)
    sigma, alpha = capsys.readouterr().out.split()
    assert abs(float(sigma) - 0.01) <= 0.001
    assert abs(float(alpha) / (210 * ns["reg"].options["noise_sigma"] ** 2) - 1) < 1e-6


def test_write_experiment_example_makes_a_file_process_reads(tmp_path, monkeypatch):
    """The example packs a user's own TIFF stacks into an experiment file (it used undefined arrays)."""
    import tifffile

    from radiokit.io import ImageKey, read
    from radiokit.pipeline import load_steps

    monkeypatch.chdir(tmp_path)
    rng = np.random.default_rng(0)
    shape = (3, 48, 64)
    tifffile.imwrite("darks.tif", rng.normal(100, 2, shape).astype(np.uint16), photometric="minisblack")
    tifffile.imwrite("flats.tif", rng.normal(3000, 30, shape).astype(np.uint16), photometric="minisblack")
    for i, name in enumerate(("step15.tif", "step20.tif", "step25.tif")):  # I/I0 = 0.5, 0.4, 0.3
        counts = 100 + 2900 * (0.5 - 0.1 * i)
        tifffile.imwrite(name, np.full((2, 48, 64), counts, np.uint16), photometric="minisblack")
    exec(compile(_block("### Write experiments as they happen"), "README.md", "exec"), {})
    f = read(tmp_path / "exp.h5")
    keys = f.meta["image_key"]
    assert (keys == ImageKey.DARK).sum() == 3 and (keys == ImageKey.FLAT).sum() == 3
    assert (keys == ImageKey.PROJECTION).sum() == 6
    steps = load_steps(tmp_path / "exp.h5", False)
    assert steps.numbers == (1, 2, 3) and steps.ratios == (0.15, 0.2, 0.25)
    # the averaged steps are the line integrals the frames were made with
    for image, t in zip(steps.images, (0.5, 0.4, 0.3)):
        assert abs(float(np.median(image)) + np.log(t)) < 0.01


def _readme_command_lines():
    """Every `radiokit ...` command the README shows with options, in sh blocks and in the text;
    ``[optional]`` parts kept, ``a|b`` alternatives taken by their first."""
    text = README.read_text()
    lines = [ln.split("#")[0] for block in re.findall(r"```sh\n(.*?)```", text, re.S) for ln in block.splitlines()]
    lines += re.findall(r"`(radiokit [^`]+)`", text)
    out = set()
    for line in lines:
        words = line.replace("[", " ").replace("]", " ").split()
        if not words or words[0] != "radiokit" or "COMMAND" in words or not any(w.startswith("-") for w in words):
            continue
        out.add(tuple(w.split("|")[0] if "|" in w and not w.startswith("tcp") else w for w in words[1:]))
    return sorted(out)


def test_readme_command_lines_use_options_that_exist():
    """A renamed or removed option, or a choice no longer offered, leaves the README's command lines
    wrong without failing anything else (prose fragments like `radiokit correct --domain linear`
    included, so each option is checked against its subcommand rather than the line parsed)."""
    import argparse

    from radiokit.cli import build_parser

    lines = _readme_command_lines()
    assert len(lines) >= 10, lines
    for words in lines:
        parser, rest = build_parser(), list(words)
        while rest and parser._subparsers is not None:  # down to the subcommand named
            subs = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
            if rest[0] not in subs.choices:
                break
            parser = subs.choices[rest.pop(0)]
        where = f"README: radiokit {' '.join(words)}"
        assert parser.prog != "radiokit", where
        for i, w in enumerate(rest):
            if w.startswith("-"):
                action = parser._option_string_actions.get(w)
                assert action is not None, f"{where}: {parser.prog} has no {w}"
                if action.choices is not None and i + 1 < len(rest):
                    value = action.type(rest[i + 1]) if action.type else rest[i + 1]
                    assert value in action.choices, f"{where}: {w} {value} is not one of {action.choices}"


def test_the_protocol_file_the_acquire_commands_name_is_shown_and_plans(tmp_path):
    """`radiokit acquire protocol.toml --dry-run` was the README's first acquisition command, but
    no protocol file was shown anywhere (only the Python dict): the one shown plans as written,
    for the lab and for the virtual bench."""
    from conftest import run_cli

    blocks = [b for b in re.findall(r"```toml\n(.*?)```", README.read_text(), re.S) if b.startswith("# protocol.toml")]
    assert len(blocks) == 1, "README shows no protocol.toml"
    (tmp_path / "protocol.toml").write_text(blocks[0])
    for extra, settle in (([], 60), (["--sim"], 0)):  # the virtual bench waits its own [sim] settle_s
        res = run_cli("acquire", "protocol.toml", "--dry-run", *extra, cwd=tmp_path)
        assert res.returncode == 0, res.stderr
        assert "32 frames" in res.stdout and "-> series.h5" in res.stdout, res.stdout
        assert f"settle {settle} s per step" in res.stdout, res.stdout
    assert sorted(p.name for p in tmp_path.iterdir()) == ["protocol.toml"]  # a dry run touches nothing


def test_the_process_option_examples_run(tmp_path):
    """The README's `radiokit process experiment.h5 --no-report` and `--cross-check ssd` lines run
    as shown on an experiment file, and do what the text beside them says. The file is a small
    synthetic one, so the ROIs are given (its square is too small for the automatic search)."""
    import json

    from conftest import run_cli, synthetic

    block = re.search(r"### Process: from an experiment file.*?```sh\n(.*?)```", README.read_text(), re.S).group(1)
    lines = {
        ln.split("#")[0].split()[-1]: ln.split("#")[0].split() for ln in block.splitlines() if "experiment.h5 --" in ln
    }
    assert set(lines) == {"--no-report", "ssd"}, lines
    synthetic(tmp_path / "experiment.h5")
    rois = ["--inclusion", "75", "86", "75", "86", "--background", "75", "86", "40", "51", "--crop-mm", "0", "-q"]
    res = run_cli(*lines["--no-report"][1:], *rois, cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    assert sorted(p.name for p in (tmp_path / "experiment").iterdir()) == [
        ".radiokit-output",
        "results.h5",
        "results.json",
    ]
    res = run_cli(*lines["ssd"][1:], *rois, "--overwrite", cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    record = json.loads((tmp_path / "experiment" / "results.json").read_text())
    check = record["registration"][record["main_pair"]]["cross_check"]
    assert check["method"] == "ssd" and check["agree"] and check["median_px"] <= check["p95_px"], check
    assert (tmp_path / "experiment" / "report.html").exists()


def test_the_first_hour_commands_run_as_written(tmp_path):
    """The "First hour" section's radiokit lines run as shown, in a folder holding what they name:
    the demo's experiment file (a small synthetic one here: `make demo` takes minutes) and a darks,
    flats and frames TIFF. Only `process` gets more: ROIs, as the synthetic square is too small for
    the automatic search. The corrected frames are -ln(I/I0) as the comment says."""
    from conftest import run_cli, synthetic

    from radiokit.io import read, write_tiff

    block = re.search(r"## First hour\n\n```sh\n(.*?)```", README.read_text(), re.S).group(1)
    lines = [ln.split("#")[0].split() for ln in block.splitlines()]
    assert [w[0] for w in lines] == ["make", ".", "radiokit", "radiokit", "radiokit", "radiokit"], lines
    (tmp_path / "out" / "demo").mkdir(parents=True)
    synthetic(tmp_path / "out" / "demo" / "experiment.h5")
    shape = (3, 32, 48)
    write_tiff(tmp_path / "darks.tif", np.full(shape, 100, np.uint16))
    write_tiff(tmp_path / "flats.tif", np.full(shape, 3100, np.uint16))
    write_tiff(tmp_path / "frames.tif", np.full(shape, 1600, np.uint16))  # I/I0 = 1500 / 3000
    rois = ["--inclusion", "75", "86", "75", "86", "--background", "75", "86", "40", "51", "--crop-mm", "0", "-q"]
    for words in lines[2:]:
        extra = rois if words[1] == "process" else ["-q"] if words[1] == "correct" else []
        res = run_cli(*words[1:], *extra, cwd=tmp_path)
        assert res.returncode == 0, (words, res.stderr)
    assert (tmp_path / "mine" / "report.html").exists() and (tmp_path / "mine" / "results.json").exists()
    corrected = read(tmp_path / "corrected.h5").data
    assert corrected.shape == shape and np.allclose(corrected, np.log(2), atol=1e-5)


def test_write_experiment_example_reads_folders_of_single_frame_and_multi_page_tiffs(tmp_path, monkeypatch):
    """The vendor software saves one TIFF per frame as often as one stack: the example takes a folder
    per kind as well, its files in name order, single-frame and multi-page mixed (a stack of 3 or 4
    frames written with photometric='minisblack', as the README says it must be)."""
    import tifffile

    from radiokit.io import ImageKey, read
    from radiokit.pipeline import load_steps

    monkeypatch.chdir(tmp_path)
    rng = np.random.default_rng(1)
    rows, cols = 40, 56
    for kind, level, n in (("darks", 100, 5), ("flats", 3000, 4)):
        (tmp_path / kind).mkdir()
        for i in range(n):  # one frame per file, as the vendor software saves them
            tifffile.imwrite(f"{kind}/{kind}_{i:03d}.tif", rng.normal(level, 2, (rows, cols)).astype(np.uint16))
    for i, name in enumerate(("step15", "step20", "step25")):  # I/I0 = 0.5, 0.4, 0.3
        (tmp_path / name).mkdir()
        counts = 100 + 2900 * (0.5 - 0.1 * i)
        tifffile.imwrite(f"{name}/a.tif", np.full((4, rows, cols), counts, np.uint16), photometric="minisblack")
        tifffile.imwrite(f"{name}/b.TIFF", np.full((rows, cols), counts, np.uint16))
        (tmp_path / name / "notes.txt").write_text("not a frame")
    exec(compile(_block("### Write experiments as they happen"), "README.md", "exec"), {})
    keys = read(tmp_path / "exp.h5").meta["image_key"]
    assert (keys == ImageKey.DARK).sum() == 5 and (keys == ImageKey.FLAT).sum() == 4
    assert (keys == ImageKey.PROJECTION).sum() == 15
    steps = load_steps(tmp_path / "exp.h5", False)
    assert steps.numbers == (1, 2, 3) and steps.ratios == (0.15, 0.2, 0.25)
    for image, t in zip(steps.images, (0.5, 0.4, 0.3)):
        assert abs(float(np.median(image)) + np.log(t)) < 0.01


def test_png_and_dicom_example(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    ns = {}
    exec(compile(_block("#### Radiographs from other labs and archives"), "README.md", "exec"), ns)
    counts = ns["counts"]
    np.testing.assert_array_equal(ns["png"].data[0], counts)
    np.testing.assert_array_equal(ns["dx"].data[0], counts.astype(np.int64) * 2 - 1000)
    assert ns["dx"].meta["bit_depth"] == 12 and abs(ns["dx"].meta["pixel_size_mm"] - 0.139) < 1e-12


def test_compressed_radiographs_example(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    ns = {}
    exec(compile(_block("#### Compressed radiographs"), "README.md", "exec"), ns)
    counts = ns["counts"]
    np.testing.assert_array_equal(ns["j2k"].data[0], counts)
    np.testing.assert_array_equal(ns["dx"].data, np.stack([counts, 4095 - counts]))


def test_make_test_worker_count_is_the_one_pytest_is_given():
    """The README's "The two commands" said six pytest-xdist workers after addopts had moved to eight."""
    import tomllib

    words = {"two": 2, "three": 3, "four": 4, "five": 5, "six": 6, "seven": 7, "eight": 8}
    said = re.search(r"on (\w+) pytest-xdist workers", README.read_text()).group(1)
    pyproject = tomllib.loads((README.parent / "pyproject.toml").read_text())
    addopts = pyproject["tool"]["pytest"]["ini_options"]["addopts"]
    assert words[said] == int(re.search(r"-n (\d+)", addopts).group(1)), (said, addopts)


def test_every_command_line_option_is_named_in_the_readme():
    """`--byteorder`, `--offset`, `register --fixed-frame` / `--retry`, `sim run --darks` / `--flats` /
    `--seed` and `acquire --verbose` were in `--help` and nowhere in the README."""
    import argparse

    from radiokit.cli import build_parser

    text, missing, parsers = README.read_text(), set(), [build_parser()]
    while parsers:
        parser = parsers.pop()
        for action in parser._actions:
            if isinstance(action, argparse._SubParsersAction):
                parsers.extend(action.choices.values())
            hidden = isinstance(action, argparse._HelpAction) or action.help == argparse.SUPPRESS
            named = [] if hidden else action.option_strings  # -o stands for --output
            if named and not any(re.search(r"(?<![\w-])" + re.escape(o) + r"(?![\w-])", text) for o in named):
                missing.add(f"{parser.prog} {named[-1]}")
    assert not missing, sorted(missing)


def test_the_demo_output_shown_has_the_lines_the_demo_prints():
    """The README's demo block showed the table alone; the demo also prints the frames it acquired
    first and where the report is last. Lines compared by their words before the first number."""
    from acquisition.demo import headline

    doms = {d: {"improvement_factor": {"1": 1.1, "2": 1.2}, "bound": {"1": 1.0, "2": 1.2}, "cnr_reference": 7.0,
                "cnr": {"1": 3.0, "2": 2.0}} for d in ("log", "negative")}  # fmt: skip
    pairs = {p: {"log": 0.9, "negative": 0.7} for p in ("1->3", "2->3", "1->2")}
    r = {"main_pair": "2->3", "domains": doms, "change_ratio": pairs, "control": {"domains": doms, "change_ratio": pairs},
         "registration": {"2->3": {"method": "rc", "ok": False, "seconds": 5.2, "folds": 0}}}  # fmt: skip
    times = {"acquire_experiment_s": 25, "acquire_control_s": 21, "process_s": 54, "total_s": 102}
    summary = {"scene": "seed-breast", "dialect": "A", "files": {"frames": 26, "per_frame_overhead_ms": 6.2},
               "results": r, "report": "out/demo/results/report.html", "timings": times}  # fmt: skip
    label = lambda line: re.split(r"[\d:]", line.strip(), maxsplit=1)[0]
    text = README.read_text()
    shown = re.search(r"```\n((?:scene|\s+log domain)[^`]*)```", text).group(1).splitlines()
    assert [label(x) for x in shown] == [label(x) for x in headline(summary).splitlines()]
