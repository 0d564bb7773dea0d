"""Start-up time of the command line: `aperture-fab --help`, `presets`, `processes`, the import.

Run: .venv/bin/python benchmarks/bench_cli.py [--repeats 7] [--json PATH]

Each command runs `--repeats` times as a fresh child process (after one untimed warm-up run,
which also writes the bytecode caches) and the wall time from spawn to exit is timed; the table
prints the median, the fastest and the slowest run. These commands need neither PyTorch nor the
mesh and plotting libraries, so they should not import them: the goal is a median under
GOAL_S (0.5 s). `aperture-fab` is the console script beside this Python (falling back to
`python -m aperture_fab.cli` when it is not installed there).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

#: The start-up goal for each command, seconds (median wall time).
GOAL_S = 0.5


def cli_command() -> list[str]:
    """The `aperture-fab` console script of this environment, or `python -m aperture_fab.cli`."""
    script = Path(sys.executable).parent / "aperture-fab"
    if script.is_file() and os.access(script, os.X_OK):
        return [str(script)]
    return [sys.executable, "-m", "aperture_fab.cli"]


def cases() -> dict[str, list[str]]:
    """Label -> command line of every timed command."""
    cli = cli_command()
    return {
        "aperture-fab --help": [*cli, "--help"],
        "aperture-fab presets": [*cli, "presets"],
        "aperture-fab processes": [*cli, "processes"],
        "python -c 'import aperture_fab'": [sys.executable, "-c", "import aperture_fab"],
    }


def time_command(command: list[str], repeats: int) -> list[float]:
    """Wall seconds of `repeats` runs of `command` (after one untimed warm-up run)."""
    subprocess.run(command, check=True, stdout=subprocess.DEVNULL)
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        subprocess.run(command, check=True, stdout=subprocess.DEVNULL)
        times.append(time.perf_counter() - start)
    return times


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=7, help="timed runs per command")
    parser.add_argument("--json", type=Path, metavar="PATH", help="also write the figures here")
    args = parser.parse_args(argv)
    if args.repeats < 1:
        parser.error("--repeats must be at least 1")
    figures: dict[str, Any] = {"goal_s": GOAL_S, "repeats": args.repeats,
                               "python": sys.version.split()[0], "cpus": os.cpu_count(),
                               "commands": {}}
    print(f"python {figures['python']}, {figures['cpus']} CPUs, {args.repeats} runs each, "
          f"goal: median under {GOAL_S} s")
    print(f"{'command':<34} {'median s':>9} {'min s':>7} {'max s':>7} {'x goal':>7}")
    for label, command in cases().items():
        times = time_command(command, args.repeats)
        median = statistics.median(times)
        figures["commands"][label] = {"command": command, "median_s": median,
                                      "min_s": min(times), "max_s": max(times),
                                      "ratio_to_goal": median / GOAL_S, "runs_s": times}
        print(f"{label:<34} {median:>9.3f} {min(times):>7.3f} {max(times):>7.3f} "
              f"{median / GOAL_S:>7.2f}")
    if args.json is not None:
        args.json.write_text(json.dumps(figures, indent=2) + "\n")
    return figures


if __name__ == "__main__":
    main()
