"""Where a design run's config travels: the functions that receive it, counted by tracing.

Runs one small seeded `aperture-fab design` (tools/output_digest.py's, 4 iterations, no STEP) in
this process with a profiler, and counts every function of the package called while
`run_design` runs that receives the resolved `Config` as an argument (a "stop"), the files they
are in and the calls; and, apart, the functions that receive one of its typed settings instead
(the optimizer's, fabrication's, validation's, photometry's: a stage reading its own table).

    python tools/config_stops.py --work /tmp/stops [--list]

Issue 19 measured 177 stops in 37 files before the config was typed; the goal is a quarter.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import threading
from collections import Counter
from pathlib import Path
from types import FrameType
from typing import Any

FLAGS = ["--iterations", "4", "--view-pixels", "48", "48", "--tolerance-samples", "2",
         "--mesh-samples", "8", "--quiet", "--seed", "7"]
PACKAGE = "aperture_fab"
SETTINGS_TYPES = ("OptimizerSettings", "FabricationSettings", "ValidationSettings",
                  "PhotometrySettings")


def trace_design(image: Path, out: Path) -> tuple[Counter[str], Counter[str]]:
    """Calls per function (file:function) that received a Config, and that received settings."""
    from aperture_fab.cli import main
    from aperture_fab.config import Config

    config_calls: Counter[str] = Counter()
    settings_calls: Counter[str] = Counter()
    inside = threading.local()

    def profile(frame: FrameType, event: str, _arg: Any) -> None:
        code = frame.f_code
        if event == "return" and code.co_name == "run_design":
            inside.on = False
        if event != "call" or PACKAGE not in code.co_filename:
            return
        if code.co_name == "run_design":
            inside.on = True
        if not getattr(inside, "on", threading.current_thread() is not threading.main_thread()):
            return
        args = [frame.f_locals.get(name) for name in code.co_varnames[:code.co_argcount
                                                                       + code.co_kwonlyargcount]]
        where = f"{code.co_filename.split(PACKAGE + '/')[-1]}:{code.co_name}"
        if any(isinstance(a, Config) for a in args):
            config_calls[where] += 1
        elif any(type(a).__name__ in SETTINGS_TYPES for a in args):
            settings_calls[where] += 1

    threading.setprofile(profile)
    sys.setprofile(profile)
    try:
        status = main(["design", str(image), "--out", str(out / "plate.stl"), *FLAGS])
    finally:
        sys.setprofile(None)
        threading.setprofile(None)
    if status not in (0, 5, 6):
        raise SystemExit(f"the design ended with exit status {status}")
    return config_calls, settings_calls


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--work", type=Path, required=True, help="an empty work folder")
    parser.add_argument("--list", action="store_true", help="list every stop")
    args = parser.parse_args()
    args.work.mkdir(parents=True, exist_ok=True)
    targets = args.work / "targets"
    subprocess.run([sys.executable, "examples/make_targets.py", "--out", str(targets)],
                   check=True, stdout=subprocess.DEVNULL)
    config_calls, settings_calls = trace_design(targets / "digit-3.png", args.work / "out")
    for label, calls in (("config", config_calls), ("settings", settings_calls)):
        files = {where.split(":")[0] for where in calls}
        print(f"{label}: {len(calls)} stops in {len(files)} files, {sum(calls.values())} calls")
        if args.list:
            for where, n in sorted(calls.items()):
                print(f"  {where} x{n}")


if __name__ == "__main__":
    main()
