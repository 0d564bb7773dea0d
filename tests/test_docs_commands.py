"""Every command in the documentation runs (issue 21, item 3), or is an example with a reason.

Which commands: every fenced block of README.md, docs/*.md, cad/README.md and
benchmarks/README.md that is a shell block (```sh, ```bash, ```shell, ```console) or whose
lines start with a command word (COMMAND_WORDS: aperture-fab, python, .venv/bin/python, ./dev,
pip, ...). In such a block each line is a command; an indented line or one after a trailing
backslash continues the one before; `# ...` comments are dropped; in a console block only the
`$ ` lines are commands (the rest is output). A block of output (`aperture-fab: error: ...`)
starts with no command word and is not one.

How each runs, as written, in bash, in a fresh copy of a workspace laid out like the checkout
(WORKSPACE below: the example images, a small design in outputs/x and outputs/demo, the
README's TOML block as my.toml, links to .venv, cad/, benchmarks/), with the project's .venv
first on PATH (so `python` and `aperture-fab` are the project's) and HOME set to the workspace
(so `~/sheets` stays inside it). The only changes to a command, all in the tables below:

- FAST_FLAGS: flags appended to a command that starts with the given words, so that a design
  takes seconds, not minutes (`--iterations 2 --no-validate`); the command's own flags stay.
- EXAMPLES: commands not run, each with the reason (a Ctrl-C to resume, a Ray cluster, an
  install, a usage synopsis, a benchmark that another test runs at its quickest settings).
- NEEDS: commands skipped, saying so, when an optional extra is not installed.

A command passes when it exits 0 (or, for design and validate, 5 or 6: the report's verdict on
the workspace's small part, which says FAIL; the command did its job). A new command in the docs
is run as written: if it fails or takes over COMMAND_TIMEOUT_S, fix the docs or the code, add
fast flags, or add it to EXAMPLES with the reason. The test ids are FILE:LINE.
"""

from __future__ import annotations

import importlib.util
import json
import os
import re
import shlex
import shutil
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
import torch
from conftest import TINY_TOML

ROOT = Path(__file__).resolve().parents[1]
#: The documentation whose commands must run.
DOC_GLOBS = ("README.md", "docs/*.md", "cad/README.md", "benchmarks/README.md")
#: Fence languages that mark a shell block.
SHELL_LANGUAGES = frozenset({"sh", "bash", "shell", "console"})
#: A block whose lines start with one of these words is a block of commands.
COMMAND_WORDS = frozenset({"aperture-fab", "python", "python3", ".venv/bin/python", "./dev",
                           "pip", "taskset"})
#: Longest a command may run, seconds; past it the test fails and says what to do.
COMMAND_TIMEOUT_S = 600

#: Flags appended to every command starting with these words (the longest match wins): the
#: workspace's designs take seconds, the benchmarks one small size.
FAST_FLAGS: dict[str, tuple[str, ...]] = {
    # The default preset's full job takes about five minutes (README, "The part as made").
    "aperture-fab design": ("--iterations", "2", "--no-validate"),
    "./dev demo": ("--iterations", "2", "--no-validate"),
    # No Monte Carlo tolerance draws and no mesh re-trace: the rest of the report is made.
    "aperture-fab validate": ("--tolerance-samples", "0", "--mesh-samples", "0"),
    ".venv/bin/python benchmarks/bench_step.py": ("--sides", "8", "--repeats", "1"),
    ".venv/bin/python benchmarks/bench_fabrication.py": ("--repeats", "1"),
}

#: The benchmark smoke tests that run a benchmark at its quickest settings.
_BENCH_TESTS = "tests/test_benchmarks_run.py runs it at its quickest settings"
_SYNOPSIS = "a usage synopsis ([optional flags], a|b choices), not a command to run"
_MEASURED = ("needs outputs/x_made, which the measure command before it writes (each command "
             "runs in a fresh workspace); tests/test_measure_judge.py measures a simulated "
             "scan and runs validate, render and display on the folder; "
             "tests/test_measure_refit.py runs display --refit")
_CLUSTER = "needs a Ray cluster (tests/test_sweep.py runs sweeps on a local Ray instance)"

#: Commands that are not run, by their text (whitespace collapsed, comment dropped), with why.
EXAMPLES: dict[str, str] = {
    "./dev test": "runs the whole test suite, this test among it (CI runs it as .ci/run)",
    "aperture-fab design img.png --out outputs/x --resume":
        "continues a design stopped by Ctrl-C, from its checkpoint; "
        "tests/test_cli.py::test_ctrl_c_saves_a_checkpoint_and_resume_finishes runs it",
    # docs/sweep.md
    "pip install 'aperture-fab[sweep]'": "installs packages (./dev setup installs the extra)",
    "aperture-fab sweep examples/sweep.toml --out outputs/sweep":
        "24 full design jobs, hours on 2 cores; the --dry-run above checks the file and every "
        "point, and tests/test_sweep.py runs small sweeps on a local Ray instance",
    "open outputs/sweep/sweep.html": "opens the page in a browser (macOS `open`)",
    "ray start --head --port=6379 --num-cpus=16": "starts a Ray cluster's head node",
    "ray start --address=HEAD_HOST:6379 --num-cpus=16": "joins a Ray cluster: HEAD_HOST",
    "aperture-fab sweep sweep.toml --address auto --out /shared/sweeps/run1": _CLUSTER,
    "aperture-fab sweep sweep.toml --address ray://HEAD_HOST:10001 --out /shared/sweeps/run1 "
    "--gather": _CLUSTER,
    # README.md, docs/measure.md: the plate as made (issue 17)
    "aperture-fab validate outputs/x_made/holes.csv img.png --keep-display": _MEASURED,
    "aperture-fab render outputs/x_made/holes.csv img.png --out view_made.png": _MEASURED,
    "aperture-fab display outputs/x_made/holes.csv img.png --eye 0,0 --pupil 4 --out "
    "frame_made.png": _MEASURED,
    "aperture-fab display --refit outputs/x_made img.png": _MEASURED,
    # docs/tracking.md
    ".venv/bin/python benchmarks/bench_display.py --repeats 7":
        "about ten minutes at 7 repeats; " + _BENCH_TESTS,
    # cad/README.md, docs/assembly.md
    ".venv/bin/python -m pip install -e '.[cad]'":
        "installs packages, about 1.3 GB (./dev setup installs the cad extra)",
    # benchmarks/README.md
    ".venv/bin/python benchmarks/bench_optimize.py": "minutes; " + _BENCH_TESTS,
    ".venv/bin/python benchmarks/bench_quality.py": "minutes; " + _BENCH_TESTS,
    ".venv/bin/python benchmarks/bench_end_to_end.py": "minutes; " + _BENCH_TESTS,
    ".venv/bin/python benchmarks/bench_light.py": "minutes; " + _BENCH_TESTS,
    ".venv/bin/python benchmarks/bench_rival_fit.py":
        "five display fits and judgements of a regular array, about two minutes; " + _BENCH_TESTS,
    ".venv/bin/python benchmarks/bench_refit.py":
        "20 made copies measured and re-fitted, about two minutes; " + _BENCH_TESTS,
    ".venv/bin/python benchmarks/bench_sweep.py":
        "starts Ray and runs design jobs: over two minutes on 2 cores even with --quick "
        "--points 2 (measured 134 s)",
    ".venv/bin/python benchmarks/bench_made_part.py":
        "designs and judges the default part with its rivals: over three minutes on 2 cores "
        "even with --quick (measured 194 s)",
    "./dev bench": "every benchmark at its default settings: an hour or more",
    ".venv/bin/python benchmarks/bench_optimize.py [--device auto|cpu|cuda] [--repeats 3] "
    "[--quick] [--large] [--json PATH]": _SYNOPSIS,
    ".venv/bin/python benchmarks/bench_quality.py [--iterations N] [--targets digit-3 letter-A "
    "...] [--device auto|cpu|cuda] [--json PATH]": _SYNOPSIS,
    "taskset -c 0,1 .venv/bin/python benchmarks/bench_end_to_end.py [--target natural] "
    "[--repeats 1] [--cache cold|warm] [--design-args \"--cells 80 80 --pitch-mm 0.25\"]":
        _SYNOPSIS,
    ".venv/bin/python benchmarks/bench_made_part.py [--targets natural digit-3 letter-A "
    "line-pairs] [--preset near-eye] [--process NAME] [--set KEY=VALUE ...] [--states 32] "
    "[--copies 4] [--rival-pitches 3] [--fit-iterations 20] [--tracked N] [--tracked-light 1] "
    "[--tracked-states 8] [--quick] [--json PATH] [--plot DIR]":
        _SYNOPSIS,
}

#: Commands starting with these words need an optional extra: (module, how to install it).
NEEDS: dict[str, tuple[str, str]] = {
    "python cad/": ("cadquery", "pip install -e '.[cad]'"),
    "aperture-fab sweep": ("ray", "pip install -e '.[sweep]'"),
}

#: Commands that take seconds (CLI start-up, no design): the rest are marked slow.
QUICK = ("aperture-fab presets", "aperture-fab processes", "aperture-fab design --help",
         "aperture-fab export", "aperture-fab assembly", "aperture-fab sweep")

#: design and validate exit 5 (FAIL) or 6 (WARN, --strict) having written the part and its
#: report; the workspace's small part is judged poor, which is not a failure of the command.
VERDICT_STATUSES = {"aperture-fab design": (5, 6), "aperture-fab validate": (5, 6)}


@dataclass(frozen=True)
class Command:
    """One command of the docs: file (relative to the checkout), line (1-based) and text (the
    shell text: continuation lines joined, comments dropped)."""

    file: str
    line: int
    text: str

    @property
    def key(self) -> str:
        """The text with its whitespace collapsed: how the tables name it."""
        return " ".join(self.text.split())

    @property
    def place(self) -> str:
        return f"{self.file}:{self.line}"


def _starts(key: str, prefix: str) -> bool:
    """Whether a command's key starts with `prefix` as whole words (or a path prefix `x/`)."""
    return key == prefix or key.startswith(prefix if prefix.endswith("/") else prefix + " ")


def _longest(key: str, table: dict[str, object] | tuple[str, ...]) -> str | None:
    matches = [prefix for prefix in table if _starts(key, prefix)]
    return max(matches, key=len) if matches else None


FENCE = re.compile(r"^(\s*)(```+|~~~+)\s*([\w+-]*)")
COMMENT = re.compile(r"(^|\s)#.*$")


def _first_word(line: str) -> str:
    words = line.strip().removeprefix("$ ").split()
    return words[0] if words else ""


def _block_commands(file: str, first_line: int, language: str, lines: list[str]
                     ) -> list[Command]:
    """The commands of one fenced block whose first content line is `first_line`."""
    console = language == "console"
    if language not in SHELL_LANGUAGES and not any(
            _first_word(line) in COMMAND_WORDS for line in lines):
        return []
    commands: list[tuple[int, list[str]]] = []
    continued = False
    for number, raw in enumerate(lines, first_line):
        text = raw.rstrip()
        if console and not continued:
            if not text.lstrip().startswith("$ "):
                continue
            text = text.lstrip()[2:]
        stripped = COMMENT.sub("", text).rstrip()
        starts_new = not continued and not (text[:1].isspace() and commands)
        continued = stripped.endswith("\\")
        stripped = stripped.removesuffix("\\").strip()
        if not stripped:
            continue
        if starts_new:
            commands.append((number, [stripped]))
        else:
            commands[-1][1].append(stripped)
    return [Command(file, number, " ".join(parts)) for number, parts in commands]


def extract_commands(path: Path, name: str) -> list[Command]:
    """Every command in the fenced blocks of the markdown file `path` (named `name`)."""
    commands: list[Command] = []
    fence: str | None = None
    language = ""
    start = 0
    block: list[str] = []
    for number, line in enumerate(path.read_text().splitlines(), 1):
        match = FENCE.match(line)
        if fence is None:
            if match:
                fence, language, start, block = match.group(2), match.group(3).lower(), number, []
        elif match and match.group(2).startswith(fence[0]) and len(match.group(2)) >= len(fence) \
                and not match.group(3):
            commands += _block_commands(name, start + 1, language, block)
            fence = None
        else:
            block.append(line)
    return commands


def doc_files() -> list[Path]:
    return sorted({p for pattern in DOC_GLOBS for p in ROOT.glob(pattern)})


def all_commands() -> list[Command]:
    return [c for path in doc_files()
            for c in extract_commands(path, path.relative_to(ROOT).as_posix())]


COMMANDS = all_commands()


def _param(command: Command) -> object:
    slow = command.key not in EXAMPLES and _longest(command.key, QUICK) is None
    return pytest.param(command, id=command.place, marks=[pytest.mark.slow] if slow else [])


# -- the parser ------------------------------------------------------------------------------

PARSER_SAMPLE = """\
Text.

```sh
aperture-fab presets            # a comment
aperture-fab design a.png \\
    --out x   # continued
```

```
aperture-fab: error: plate.gap_mm = 8 ... (output, not a command)
```

```
.venv/bin/python bench.py [--quick]
                          [--json PATH]
```

```console
$ aperture-fab processes
resin: ...
```

```toml
preset = "near-eye"
```
"""


def test_the_parser_finds_commands_continuations_and_skips_output(tmp_path: Path) -> None:
    path = tmp_path / "sample.md"
    path.write_text(PARSER_SAMPLE)
    found = [(c.line, c.key) for c in extract_commands(path, "sample.md")]
    assert found == [(4, "aperture-fab presets"),
                     (5, "aperture-fab design a.png --out x"),
                     (14, ".venv/bin/python bench.py [--quick] [--json PATH]"),
                     (19, "aperture-fab processes")]


def test_the_docs_have_the_commands_this_test_knows() -> None:
    """The extraction sees the README's blocks, and every table entry names a command that is
    in the docs (a changed command leaves no stale entry behind)."""
    keys = [c.key for c in COMMANDS]
    assert "aperture-fab presets" in keys and "./dev demo" in keys
    assert {c.file for c in COMMANDS} >= {"README.md", "docs/sweep.md", "docs/tracking.md",
                                         "cad/README.md", "benchmarks/README.md"}
    stale = [key for key in EXAMPLES if key not in keys]
    stale += [prefix for table in (FAST_FLAGS, NEEDS, VERDICT_STATUSES)
              for prefix in table if not any(_starts(key, prefix) for key in keys)]
    assert not stale, f"table entries that match no command in the docs: {stale}"
    assert all(reason.strip() for reason in EXAMPLES.values())


def test_the_readme_config_block_resolves() -> None:
    """The README's TOML block (the workspace's my.toml) is a valid config, its [process]
    table included (read when the part is made)."""
    from aperture_fab.config.config import parse_toml, resolve


    config = resolve(None, parse_toml(readme_config(), "README.md"))
    assert config.scene.plate.cells == (40, 40)
    assert config.fabrication.process.name == "photomask"


def readme_python(first_line: str) -> str:
    """The README's ```python block that starts with `first_line`."""
    blocks = re.findall(r"^```python\n(.*?)^```", (ROOT / "README.md").read_text(), re.S | re.M)
    found = [b for b in blocks if b.startswith(first_line)]
    assert found, f"README.md has no ```python block starting {first_line!r}"
    return found[0]


@pytest.mark.slow
@pytest.mark.usefixtures("one_torch_thread")
def test_the_readme_api_example_runs(workspace: Path, monkeypatch: pytest.MonkeyPatch,
                                     capsys: pytest.CaptureFixture[str]) -> None:
    """The README's commands-as-functions block, run as written in a fresh folder with the
    example targets (a minute on 2 cores): each function returns its command's value."""
    base = workspace.parent / "api_example"
    shutil.copytree(workspace / "examples" / "targets", base / "examples" / "targets")
    monkeypatch.chdir(base)
    namespace: dict[str, Any] = {}
    exec(compile(readme_python("# The commands as functions"), "README.md", "exec"), namespace)
    assert namespace["made"].part.layout.count > 0
    assert namespace["levels"]["tolerance"] in ("pass", "warn", "fail")
    assert (base / "outputs" / "api" / "dxf" / "plate.dxf").is_file()
    assert namespace["view"].psnr_db is not None and namespace["view"].path.is_file()
    assert "holes;" in capsys.readouterr().out


@pytest.mark.slow
@pytest.mark.usefixtures("one_torch_thread")
def test_the_readme_in_memory_example_runs(tmp_path: Path, monkeypatch: pytest.MonkeyPatch
                                           ) -> None:
    """The README's in-memory design block, run as written: the part's files, the verdicts and
    the report come back as values and nothing is written."""
    monkeypatch.chdir(tmp_path)
    namespace: dict[str, Any] = {}
    exec(compile(readme_python("# The design job in memory"), "README.md", "exec"), namespace)
    made = namespace["made"]
    from aperture_fab.fabrication.mesh_checks import check_mesh
    from aperture_fab.io.formats import read_stl

    checked = check_mesh(read_stl(made.part_files["plate.stl"]))  # the bytes are the part
    assert checked.watertight and checked.genus == made.part.layout.count > 0
    assert made.verdicts and made.verdicts == made.report.verdicts
    assert made.report.level in ("pass", "warn", "fail")
    assert set(made.report_files) == {"report.json", "report.html", "views.npz"}
    assert json.loads(made.report_files["report.json"]) == made.report.as_json()
    assert list(tmp_path.iterdir()) == []  # nothing written


# -- the workspace ---------------------------------------------------------------------------

def readme_config() -> str:
    """The README's first ```toml block: the whole scene as a config file."""
    text = (ROOT / "README.md").read_text()
    match = re.search(r"^```toml\n(.*?)^```", text, re.S | re.M)
    assert match, "README.md has no ```toml config block"
    return match.group(1)


#: Links in the workspace to the checkout's own folders and files (read, not written).
LINKED = (".venv", "cad", "benchmarks", "dev", "pyproject.toml")


@pytest.fixture(scope="module")
def workspace(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """WORKSPACE: a folder laid out like the checkout for the docs' commands.

    img.png and target.png: the grey marker (32 x 32); a.png, b.png: two example targets;
    my.toml: the README's TOML block; tiny.toml: conftest's TINY_TOML; outputs/x and
    outputs/demo: a design of img.png with tiny.toml (16 x 16 holes, no validation) made once,
    so that validate, render, display, export, assembly and cad/ run in seconds; edited.stl:
    its plate.stl; examples/: the checkout's, with examples/targets made; links to LINKED.
    """
    from aperture_fab.cli import main
    from aperture_fab.io.images import encode_png
    from aperture_fab.targets import asymmetric_marker, digit, pixel_art

    base = tmp_path_factory.mktemp("docs_workspace")
    marker = encode_png(asymmetric_marker(32))
    for name in ("img.png", "target.png"):
        (base / name).write_bytes(marker)
    (base / "a.png").write_bytes(encode_png(digit("3", 32)))
    (base / "b.png").write_bytes(encode_png(pixel_art(32)))
    (base / "my.toml").write_text(readme_config())
    (base / "tiny.toml").write_text(TINY_TOML)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        status = main(["design", str(base / "img.png"), "--config", str(base / "tiny.toml"),
                       "--out", str(base / "outputs" / "x" / "plate.stl"), "--no-validate",
                       "--quiet"])
    finally:
        torch.set_num_threads(threads)
    assert status == 0
    shutil.copytree(base / "outputs" / "x", base / "outputs" / "demo")
    shutil.copy(base / "outputs" / "x" / "plate.stl", base / "edited.stl")
    shutil.copytree(ROOT / "examples", base / "examples",
                    ignore=shutil.ignore_patterns("targets", "__pycache__"))
    subprocess.run([sys.executable, "examples/make_targets.py", "--out", "examples/targets"],
                   cwd=base, check=True, capture_output=True)
    for name in LINKED:
        (base / name).symlink_to(ROOT / name)
    return base


def _skip_reason(command: Command) -> str | None:
    """Why a runnable command cannot run here (a missing extra, ./dev before set-up)."""
    need = _longest(command.key, NEEDS)
    if need is not None:
        module, install = NEEDS[need]
        if importlib.util.find_spec(module) is None:
            return f"needs {module}, not installed ({install})"
    if command.key.startswith("./dev"):
        stamp = ROOT / ".venv" / ".installed"
        if not stamp.exists() or (ROOT / "pyproject.toml").stat().st_mtime > stamp.stat().st_mtime:
            return "./dev would set up .venv first (no current .venv/.installed)"
    return None


@pytest.mark.usefixtures("one_torch_thread")
@pytest.mark.parametrize("command", [_param(c) for c in COMMANDS])
def test_every_doc_command_runs_or_is_an_example(command: Command, workspace: Path,
                                                 tmp_path: Path) -> None:
    if command.key in EXAMPLES:
        pytest.skip(f"example, not run: {EXAMPLES[command.key]}")
    reason = _skip_reason(command)
    if reason is not None:
        pytest.skip(reason)
    work = tmp_path / "work"
    shutil.copytree(workspace, work, symlinks=True)
    fast = _longest(command.key, FAST_FLAGS)
    script = command.text + ("" if fast is None else " " + shlex.join(FAST_FLAGS[fast]))
    env = {**os.environ, "HOME": str(work), "MPLBACKEND": "Agg",
           "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}"}
    start = time.perf_counter()
    try:
        done = subprocess.run(["bash", "-c", script], cwd=work, env=env, capture_output=True,
                              text=True, timeout=COMMAND_TIMEOUT_S)
    except subprocess.TimeoutExpired:
        pytest.fail(f"{command.place}: `{script}` ran over {COMMAND_TIMEOUT_S} s; give it fast "
                    "flags (FAST_FLAGS) or mark it as an example with the reason (EXAMPLES) in "
                    "tests/test_docs_commands.py")
    seconds = time.perf_counter() - start
    verdict = _longest(command.key, VERDICT_STATUSES)
    allowed = (0, *(VERDICT_STATUSES[verdict] if verdict else ()))
    assert done.returncode in allowed, (
        f"{command.place}: `{script}` exited {done.returncode} after {seconds:.0f} s (allowed: "
        f"{allowed}); fix the docs or the code, or mark it in EXAMPLES with the reason.\n"
        f"stdout:\n{done.stdout[-3000:]}\nstderr:\n{done.stderr[-3000:]}")
