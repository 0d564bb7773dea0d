"""The report's verdict is the exit status (issue 21, item 1): `design` and `validate` exit
EXIT_REPORT_FAIL when their report says FAIL, EXIT_REPORT_WARN for a WARN with --strict, else 0;
their last line (the only one with -q) carries the verdict. The files are written either way.

Most cases stand in a fake job for the optimizer and the validation (the CLI's part is what is
tested, and a real design per case would take minutes); one tiny design runs end to end.
"""

from __future__ import annotations

import contextlib
import io
import json
import re
from collections.abc import Callable
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import pytest
from conftest import design_tiny

import aperture_fab.pipeline.design_job as design_job
import aperture_fab.pipeline.validate_job as validate_job
from aperture_fab.cli import (
    EXIT_CODES_HELP,
    EXIT_OK,
    EXIT_REPORT_FAIL,
    EXIT_REPORT_WARN,
    EXIT_USAGE,
    main,
)
from aperture_fab.validation.report import Verdict, overall_level

pytestmark = pytest.mark.usefixtures("one_torch_thread")

README = Path(__file__).resolve().parents[1] / "README.md"
NAMES = ("marker",)
#: A quick validation: few tolerance samples and mesh rays.
FAST_VALIDATION = ["--tolerance-samples", "2", "--mesh-samples", "8"]


def verdict(topic: str, level: str, text: str) -> Verdict:
    return Verdict(topic, level, text)


#: The fake reports do not judge the eye distribution (their eye_distribution block is null).
EYES = verdict("eye distribution", "info", "Not judged over the eye distribution.")
NOTE = verdict("nominal", "info", "At the nominal eye point the view scores 20.0 dB PSNR.")
#: Report verdicts (most important first) for each overall level, and the check that decides
#: it: the first verdict at that level. Each text has two sentences: the line quotes the first.
REPORTS: dict[str, tuple[list[Verdict], str | None]] = {
    "pass": ([EYES, verdict("made part", "pass", "As made, 5 dB better. Make it."),
              verdict("tolerance", "pass", "All 16 parts score above 7.2 dB. At least 90 %."),
              NOTE], None),
    "warn": ([EYES,
              verdict("tolerance", "warn", "88 % of 16 parts score above 7.2 dB. Median 9 dB."),
              verdict("light", "warn", "The view is mesopic. Raise the panel."), NOTE],
             "tolerance"),
    "fail": ([EYES, verdict("made part", "fail", "As made, 6.1 dB worse than the regular array "
                            "(e.g. 0.92 % light). A plain regular pinhole array would look "
                            "better."),
              verdict("light", "warn", "The view is mesopic. Raise the panel."), NOTE],
             "made part"),
    "info": ([EYES, NOTE], None),
}
#: The exit status by (overall level, --strict).
STATUS = {("pass", False): EXIT_OK, ("pass", True): EXIT_OK,
          ("warn", False): EXIT_OK, ("warn", True): EXIT_REPORT_WARN,
          ("fail", False): EXIT_REPORT_FAIL, ("fail", True): EXIT_REPORT_FAIL,
          ("info", False): EXIT_OK, ("info", True): EXIT_OK}
#: What the one-line result starts with, by level (the words report.html and the table use).
WORD = {"pass": "PASS", "warn": "WARN", "fail": "FAIL", "info": "NOTE"}


def fake_design(verdicts: list[Verdict]) -> Callable[..., Any]:
    """run_design's stand-in: no optimizer, the given report verdicts (none without validation)."""

    def run(targets: Any, out: Path, config: Any, *, validation: Any = None, **_: Any) -> Any:
        design = SimpleNamespace(loss_history=[1.0, 0.5], stopped="completed")
        return SimpleNamespace(design=design, names=NAMES, part=None, timings_s={},
                               metrics={"eye_distribution": None,
                                        "optimized": {"psnr_db": [20.0]}},
                               verdicts=() if validation is None else tuple(verdicts))

    return run


def fake_validate(verdicts: list[Verdict]) -> Callable[..., Any]:
    """run_validate's stand-in: publishes a report.json with the given verdicts and returns
    it, as the job does (the command takes the verdicts from the returned report)."""

    def run(part: Path, targets: Any, *, out: Path, **_: Any) -> Any:
        out.mkdir(parents=True)
        report = SimpleNamespace(verdicts=tuple(verdicts), eye_distribution=None)
        (out / "report.json").write_text(json.dumps(
            {"verdicts": [v.as_dict() for v in verdicts], "eye_distribution": None}))
        layout = SimpleNamespace(count=3, violations=[])
        return SimpleNamespace(folder=out, kind="holes", names=NAMES, timings_s={},
                               part=SimpleNamespace(layout=layout), display_source="kept",
                               validation=SimpleNamespace(
                                   metrics={"as_built": {"marker": {"psnr_db": 20.0}}}),
                               report=report)

    return run


@pytest.fixture
def run_cli(tmp_path: Path, tiny_toml: Path, marker_png: Path, monkeypatch: pytest.MonkeyPatch,
            capsys: pytest.CaptureFixture[str]) -> Callable[..., tuple[int, list[str], Path]]:
    """run_cli(command, level, *flags) -> (status, stdout lines, the report's folder): design or
    validate on a report whose overall verdict is `level`."""
    calls = {"n": 0}

    def run(command: str, level: str, *flags: str) -> tuple[int, list[str], Path]:
        verdicts = REPORTS[level][0]
        calls["n"] += 1
        out = tmp_path / f"run{calls['n']}"
        if command == "design":
            monkeypatch.setattr(design_job, "run_design", fake_design(verdicts))
            argv = ["design", str(marker_png), "--config", str(tiny_toml), "--out", str(out)]
        else:
            monkeypatch.setattr(validate_job, "run_validate", fake_validate(verdicts))
            argv = ["validate", str(tmp_path / "holes.csv"), str(marker_png), "--out", str(out)]
        capsys.readouterr()
        code = main([*argv, *flags])
        return code, capsys.readouterr().out.splitlines(), out

    return run


@pytest.mark.parametrize("strict", [False, True], ids=["default", "strict"])
@pytest.mark.parametrize("level", list(REPORTS))
@pytest.mark.parametrize("command", ["design", "validate"])
def test_the_exit_status_is_the_reports_verdict(run_cli: Callable[..., Any], command: str,
                                                level: str, strict: bool) -> None:
    assert overall_level(REPORTS[level][0]) == level  # the setup
    code, _, _ = run_cli(command, level, "-q", *(["--strict"] if strict else []))
    assert code == STATUS[level, strict]


@pytest.mark.parametrize("level", list(REPORTS))
@pytest.mark.parametrize("command", ["design", "validate"])
def test_quiet_prints_one_line_that_carries_the_verdict(run_cli: Callable[..., Any],
                                                        command: str, level: str) -> None:
    _, lines, out = run_cli(command, level, "-q")
    assert len(lines) == 1, lines
    line = lines[0]
    assert line.startswith(f"{WORD[level]}: wrote {out}/ ("), line
    assert f"{out / 'report.html'} says " in line
    verdicts, deciding = REPORTS[level]
    if deciding is None:
        return
    first = next(v for v in verdicts if v.topic == deciding)
    sentence, rest = re.split(r"(?<=\.) (?=[A-Z])", first.text)  # not at "e.g. 0.92"
    count = sum(v.level == level for v in verdicts)
    topic = deciding if count == 1 else f"{count} checks {level}, first {deciding}"
    assert line.endswith(f"; {topic}: {sentence}"), line
    assert rest not in line  # the rest, and the fix, are in the report


@pytest.mark.parametrize("level", list(REPORTS))
@pytest.mark.parametrize("command", ["design", "validate"])
def test_the_last_line_states_the_outcome(run_cli: Callable[..., Any], command: str,
                                          level: str) -> None:
    _, quiet, quiet_out = run_cli(command, level, "-q")
    _, lines, out = run_cli(command, level)
    assert len(lines) > 1  # the tables first
    assert lines[-1] == quiet[0].replace(str(quiet_out), str(out))


def test_strict_says_why_a_warn_fails(run_cli: Callable[..., Any]) -> None:
    code, lines, _ = run_cli("design", "warn", "-q", "--strict")
    assert code == EXIT_REPORT_WARN
    assert f"--strict refuses it: exit status {EXIT_REPORT_WARN}" in lines[0]


def test_design_and_validate_print_the_same_verdicts(run_cli: Callable[..., Any]) -> None:
    """One function prints the verdict table for both: the lines before the nominal table."""
    printed = {}
    for command in ("design", "validate"):
        _, lines, _ = run_cli(command, "fail")
        printed[command] = lines[:lines.index("PSNR after gain (dB), nominal eye position:")]
    assert printed["design"] == printed["validate"]
    assert any(line.startswith("made part: FAIL: As made") for line in printed["design"])
    assert any(line.startswith("light: WARN: The view is mesopic") for line in printed["design"])


def test_without_validation_the_line_says_so_and_strict_is_refused(
        run_cli: Callable[..., Any], capsys: pytest.CaptureFixture[str]) -> None:
    code, lines, out = run_cli("design", "fail", "-q", "--no-validate")
    assert code == EXIT_OK  # nothing was judged, so nothing refuses the part
    assert len(lines) == 1 and lines[0].startswith(f"NOT VALIDATED: wrote {out}/")
    assert f"aperture-fab validate {out / 'plate.stl'}" in lines[0]
    with pytest.raises(SystemExit) as stop:
        run_cli("design", "fail", "--no-validate", "--strict")
    assert stop.value.code == EXIT_USAGE
    assert "--strict" in capsys.readouterr().err


@pytest.mark.parametrize(("command", "last"), [(["presets"], "3 presets: "),
                                                (["processes"], " processes: ")])
def test_the_listings_end_with_a_summary_line(command: list[str], last: str,
                                              capsys: pytest.CaptureFixture[str]) -> None:
    assert main(command) == EXIT_OK
    assert last in capsys.readouterr().out.splitlines()[-1]


def test_the_help_and_the_readme_list_every_exit_status(
        capsys: pytest.CaptureFixture[str]) -> None:
    import aperture_fab.cli as cli

    codes = {value for name, value in vars(cli).items()
             if name.startswith("EXIT_") and isinstance(value, int)}
    table = {int(m[1]) for m in re.finditer(r"^\| (\d+) \|", README.read_text(), re.M)}
    assert table == codes
    helped = {int(m[1]) for m in re.finditer(r"^  (\d+) ", EXIT_CODES_HELP, re.M)}
    assert helped == codes
    for command in ("design", "validate"):
        with pytest.raises(SystemExit):
            main([command, "--help"])
        assert "--strict" in capsys.readouterr().out


@pytest.mark.parametrize(("module", "name", "status"), [
    ("aperture_fab.fabrication.process", "UnmakeableError", "EXIT_FAILED"),
    ("aperture_fab.optimize.optimizer", "DivergedError", "EXIT_FAILED"),
    ("aperture_fab.sweep.cluster", "ClusterUnreachable", "EXIT_NO_CLUSTER"),
])
def test_an_error_class_carries_its_exit_status(module: str, name: str, status: str) -> None:
    """The status comes from the class (aperture_fab.errors), and a subclass inherits it; the
    error keeps its Python kind, which the jobs catch it by."""
    import importlib

    import aperture_fab.cli as cli
    from aperture_fab.cli.status import exit_code

    kind = getattr(importlib.import_module(module), name)
    err = type("Sub", (kind,), {})("why")
    assert exit_code(kind("why")) == exit_code(err) == getattr(cli, status)
    assert isinstance(err, ValueError | FloatingPointError | ConnectionError)
    assert exit_code(ValueError("x")) == cli.EXIT_BAD_INPUT
    assert exit_code(PermissionError("x")) == cli.EXIT_CANNOT_WRITE


# --- end to end: a real tiny design, whose report fails ---------------------------------------


@pytest.fixture(scope="module")
def failed(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, int, list[str]]:
    """A tiny design (8 iterations) with its validation, -q: far from a good part, so its report
    says FAIL. (folder, the exit status, the lines it printed)."""
    folder = tmp_path_factory.mktemp("failed")
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        code = design_tiny(folder, "--out", str(folder / "out"), "-q", *FAST_VALIDATION)
    return folder, code, printed.getvalue().splitlines()


def test_a_failing_design_exits_with_the_fail_status_and_writes_everything(
        failed: tuple[Path, int, list[str]]) -> None:
    folder, code, lines = failed
    out = folder / "out"
    report = json.loads((out / "report.json").read_text())
    assert overall_level([SimpleNamespace(**v) for v in report["verdicts"]]) == "fail"
    assert code == EXIT_REPORT_FAIL
    for name in ("plate.stl", "holes.csv", "design.npz", "report.html"):
        assert (out / name).is_file(), name  # written: the user reads why
    first = next(v for v in report["verdicts"] if v["level"] == "fail")
    assert len(lines) == 1, lines
    assert lines[0].startswith(f"FAIL: wrote {out}/ (8 iterations"), lines[0]
    assert f"first {first['topic']}: " in lines[0] or f"; {first['topic']}: " in lines[0]


def test_validate_of_a_failing_part_says_fail_last(failed: tuple[Path, int, list[str]],
                                                  capsys: pytest.CaptureFixture[str]) -> None:
    folder, _, _ = failed
    check = folder / "check"
    capsys.readouterr()
    code = main(["validate", str(folder / "out" / "plate.stl"), str(folder / "marker.png"),
                 "--out", str(check), *FAST_VALIDATION])
    lines = capsys.readouterr().out.splitlines()
    assert code == EXIT_REPORT_FAIL
    assert lines[-1].startswith(f"FAIL: wrote {check}/ (")
    assert f"{check / 'report.html'} says do not make this part as it is; " in lines[-1]
    report = json.loads((check / "report.json").read_text())
    first = next(v for v in report["verdicts"] if v["level"] == "fail")
    assert f"{first['topic']}: FAIL: " in "\n".join(lines[:-1])  # the table, as design's
