"""What the command line prints: the one-line result, stages, warnings, the design's tables and the
report's judgement."""

from __future__ import annotations

import re
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from aperture_fab.cli.status import EXIT_OK, EXIT_REPORT_FAIL, EXIT_REPORT_WARN

if TYPE_CHECKING:  # the CLI imports the judging code only when it runs
    from aperture_fab.validation.report import Verdict

__all__ = ["Judgement", "Output", "print_design_tables", "print_eye_distribution", "report_forced",
           "show_warning"]


#: Warnings raised from this package's files are the tool's own (printed as one line).
PACKAGE_DIR = str(Path(__file__).resolve().parent.parent)


#: What the report's overall verdict says of the part, in the one-line result.
VERDICT_WORDS = {
    "fail": "do not make this part as it is",
    "warn": "usable, with reservations",
    "pass": "every check passed",
    "info": "no check was judged",
}


#: A sentence ends at . ! or ? before a capital: not inside "0.92 %" or "(e.g. the".
SENTENCE_END = re.compile(r"(?<=[.!?])\s+(?=[A-Z])")


#: The one-line result quotes the deciding verdict's first sentence up to this many characters, a
#: guard against a text without a sentence end; report.html holds the whole text and the fix.
REASON_CHARS = 400


@dataclass(frozen=True)
class Output:
    """How much the command prints, chosen once in `main` and passed down (args.output).

    quiet: only errors and the final one-line result. verbose: tracebacks and stage timings.
    terminal: stderr is a terminal, so progress bars may redraw it; otherwise (a log) each
    stage is one plain line.
    """

    quiet: bool
    verbose: bool
    terminal: bool

    @property
    def progress(self) -> bool:
        """Whether to draw progress bars (tqdm writes carriage returns, unreadable in a log)."""
        return self.terminal and not self.quiet

    def result(self, line: str) -> None:
        """The final one-line result: the last line printed, and the only one with --quiet."""
        print(line)

    def detail(self, line: str) -> None:
        """A result line beyond the final one (tables, notes): not with --quiet."""
        if not self.quiet:
            print(line)

    def stage(self, line: str) -> None:
        """A stage starting, as a plain line on stderr when there are no progress bars."""
        if not self.quiet and not self.terminal:
            print(f"aperture-fab: {line}", file=sys.stderr, flush=True)

    def timings(self, timings_s: dict[str, float]) -> None:
        """Seconds per stage, with --verbose."""
        if self.verbose and timings_s:
            print("timings: " + ", ".join(f"{k.removesuffix('_s')} {v:.2f} s"
                                          for k, v in timings_s.items()), file=sys.stderr)

    def warn(self, line: str) -> None:
        if not self.quiet:
            print(f"aperture-fab: warning: {line}", file=sys.stderr)

    def interrupted(self, line: str) -> None:
        """Ctrl-C: not an error, but said even with --quiet."""
        print(f"aperture-fab: interrupted {line}", file=sys.stderr)

    def error(self, line: str) -> None:
        print(f"aperture-fab: error: {line}", file=sys.stderr)

    def traceback(self) -> None:
        """The traceback of the exception being handled, with --verbose."""
        if self.verbose:
            import traceback

            traceback.print_exc()


def report_forced(output: Output, part: Any, config: Any, fabrication: Any) -> None:
    """With --force, say honestly how many holes break which of the process's rules (the part
    is written as designed, not fixed): quantize's resolved violations undercount them."""
    from aperture_fab.fabrication.rules import layout_violations

    if not fabrication.force:
        return
    broken = layout_violations(part.layout, config.scene.plate, fabrication.process)
    if not broken:
        return
    holes: dict[str, set[Any]] = {}
    for v in broken:
        holes.setdefault(v.rule, set()).add(v.cell)
    rules = ", ".join(f"{rule}: {'the whole plate' if cells == {None} else f'{len(cells)} holes'}"
                      for rule, cells in holes.items())
    cells = {c for v in broken if v.cell is not None for c in [v.cell]}
    output.warn(f"--force: {len(cells)} of {part.layout.count} holes break process "
                f"{fabrication.process.name}'s rules ({rules}); written anyway, as designed. The "
                "process may not make them: see `aperture-fab processes`, or drop --force.")


#: Width of a column of the eye-distribution table ("28.1 / 30.4 / 31.2").
EYE_COLUMN = 22


def print_eye_distribution(metrics: dict[str, Any], names: Sequence[str], *,
                            validated: bool, verdicts: Sequence[Verdict] = ()) -> None:
    """The design table's lead: PSNR p10 / median / p90 over the eye distribution per variant
    and target, then the eye-distribution verdict (or why there is none), the part as made
    against the best regular array, the report's other warnings and failures, and the fix the
    report recommends (its others are in the report)."""
    import textwrap

    from aperture_fab.validation.verdicts import LEVEL_WORDS, MADE_TOPIC, NOT_JUDGED, fix_plan

    headline = metrics.get("eye_distribution")
    if headline is None:
        why = NOT_JUDGED if validated else (
            "Not judged over the eye distribution (--no-validate): the PSNR below is for the "
            "nominal eye point only.")
        print(textwrap.fill("eye distribution: " + why, 100, subsequent_indent="  "))
    else:
        _print_eye_table(headline, names)
    # The part as made against the best regular array, whatever its level; then the report's
    # other judged findings that need action (light, contrast, tolerances...), which the final
    # line's verdict may name even when the eye distribution was not judged.
    for other in verdicts:
        if other.topic == MADE_TOPIC or (other.level in ("fail", "warn")
                                         and other.topic != "eye distribution"):
            print(textwrap.fill(f"{other.topic}: {LEVEL_WORDS[other.level]}: {other.text}",
                                100, subsequent_indent="  "))
    plan = fix_plan(verdicts)
    if plan.recommended is not None and plan.deciding is not None:
        others = (f" ({len(plan.alternatives)} other fixes in the report)"
                  if plan.alternatives else "")
        print(textwrap.fill(f"recommended fix ({plan.deciding.topic}): {plan.recommended}"
                            + others, 100, subsequent_indent="  "))


def _print_eye_table(headline: dict[str, Any], names: Sequence[str]) -> None:
    """PSNR p10 / median / p90 over the eye distribution per variant and target, and its
    verdict."""
    import textwrap

    from aperture_fab.validation.verdicts import LEVEL_WORDS

    variants = headline["variants"]
    print(f"PSNR over the eye distribution (dB), p10 / median / p90, {headline['states']} "
          "states:")
    print(f"  {'target':<16}" + "".join(f"{v:>{EYE_COLUMN}}" for v in variants))
    for t, name in enumerate(names):
        cells = []
        for values in variants.values():
            psnr = values["psnr_db"]
            cell = " / ".join("-" if psnr[k][t] is None else f"{psnr[k][t]:.1f}"
                              for k in ("p10", "p50", "p90"))
            cells.append(f"{cell:>{EYE_COLUMN}}")
        print(f"  {name:<16}" + "".join(cells))
    verdict = headline.get("verdict")
    if verdict is not None:
        print(textwrap.fill(f"eye distribution: {LEVEL_WORDS[verdict['level']]}: "
                            f"{verdict['text']}", 100, subsequent_indent="  "))


@dataclass(frozen=True)
class Judgement:
    """A report's overall verdict, for the exit status and the one-line result.

    level: fail, warn, pass or info: the report page's headline (`overall_level`, its
    worst judged verdict), so the terminal and the page always agree. deciding: the first
    verdict at that level (the report lists the most important first), None for info.
    count: how many verdicts are at that level.
    """

    level: str
    deciding: Verdict | None
    count: int

    @classmethod
    def of(cls, verdicts: Sequence[Verdict]) -> Judgement:
        from aperture_fab.validation.report import overall_level

        level = overall_level(verdicts)
        at_level = [v for v in verdicts if v.level == level]
        return cls(level, at_level[0] if level != "info" else None, len(at_level))

    def status(self, strict: bool) -> int:
        """EXIT_REPORT_FAIL for FAIL; EXIT_REPORT_WARN for WARN with --strict; else EXIT_OK."""
        if self.level == "fail":
            return EXIT_REPORT_FAIL
        return EXIT_REPORT_WARN if self.level == "warn" and strict else EXIT_OK

    def line(self, wrote: str, report: Path, strict: bool) -> str:
        """The one-line result: the verdict, what was written, where the report is and, for
        FAIL or WARN, the deciding check's topic and the first sentence of its reason."""
        from aperture_fab.validation.verdicts import LEVEL_WORDS

        words = VERDICT_WORDS[self.level]
        if self.level == "warn" and strict:
            words += f" (--strict refuses it: exit status {EXIT_REPORT_WARN})"
        text = f"{LEVEL_WORDS[self.level]}: {wrote} - {report} says {words}"
        if self.deciding is None or self.level == "pass":
            return text
        reason = " ".join(SENTENCE_END.split(self.deciding.text.strip(), 1)[0].split())
        if len(reason) > REASON_CHARS:
            reason = reason[:REASON_CHARS].rsplit(" ", 1)[0] + " ..."
        topic = self.deciding.topic
        if self.count > 1:
            topic = f"{self.count} checks {self.level}, first {topic}"
        return f"{text}; {topic}: {reason}"


def print_design_tables(result: Any, fabrication: Any, *, validated: bool) -> None:
    """design's tables: the verdicts (as validate prints them), the nominal PSNR and the part."""
    m = result.metrics
    print_eye_distribution(m, result.names, validated=validated, verdicts=result.verdicts)
    nominal = [v for v in m if v != "eye_distribution"]
    print("PSNR after gain (dB), nominal eye position:")
    header = f"  {'target':<16}" + "".join(f"{v:>18}" for v in nominal)
    print(header)
    for t, name in enumerate(result.names):
        print(f"  {name:<16}" + "".join(f"{m[v]['psnr_db'][t]:>18.2f}" for v in nominal))
    if result.part is None:
        return
    layout = result.part.layout
    if fabrication.force:  # nothing was resolved: the warning above counts what breaks
        print(f"part: {layout.count} holes as designed (--force); "
              f"{result.part.report.face_count} triangles, watertight")
        return
    print(f"part: {layout.count} holes, {len(layout.violations)} rule violation(s) resolved; "
          f"{result.part.report.face_count} triangles, watertight")
    for v in layout.violations[:10]:
        print(f"  {v.rule}: {v.resolution}")


def show_warning(output: Output, default: Any) -> Any:
    """A warnings.showwarning that prints the tool's own warnings as one line each (not with -q)
    and leaves every other library's warning to `default`."""

    def show(message: Warning | str, category: type[Warning], filename: str, lineno: int,
             file: Any = None, line: str | None = None) -> None:
        if filename.startswith(PACKAGE_DIR):
            output.warn(str(message))
        else:
            default(message, category, filename, lineno, file, line)

    return show
