"""Digest of a seeded design job's outputs, to prove a refactor changed no output byte.

Runs `aperture-fab design` (small, seeded, every format), `validate` and `render` into a
folder and prints one SHA-256 per file. Fields that legitimately differ between two runs of
the same code are normalized first: stage timings and package versions, the report's digest
of them, the 3MF zip timestamps, the manifest's time and hashes, the DXF header (dates, GUIDs),
the STEP header date, the report's date (report.json's run.date and the page's header), the
work folder's and the checkout's paths.

    python tools/output_digest.py --work /tmp/digest > before.txt
    (change the code)
    python tools/output_digest.py --work /tmp/digest2 > after.txt
    diff before.txt after.txt     # empty: every output is byte-identical after normalizing
"""

from __future__ import annotations

import argparse
import hashlib
import json
import re
import subprocess
import sys
import zipfile
from pathlib import Path

DESIGN_FLAGS = ["--iterations", "12", "--view-pixels", "48", "48", "--tolerance-samples", "2",
                "--mesh-samples", "8", "--step", "--quiet", "--seed", "7"]
TIMING_SECTION = re.compile(r'<section id="timings">.*?</section>', re.DOTALL)
REPORT_DIGEST = re.compile(r"report digest [0-9a-f]+")
REPORT_DATE = re.compile(r'<span class="date">[^<]*</span>')
DXF_ENTITIES = re.compile(rb"\n\s*2\r?\nENTITIES\r?\n.*?\nENDSEC", re.DOTALL)
STEP_DATE = re.compile(rb"FILE_NAME\('([^']*)','[^']*'")
#: The checkout that ran (two checkouts of the same code give the same digests).
REPO = Path(__file__).resolve().parents[1]


def normalized(path: Path, work: Path) -> bytes:
    """The file's bytes with run-to-run noise (timings, dates, the work folder) removed."""
    data = path.read_bytes().replace(str(work).encode(), b"<work>")
    data = data.replace(str(REPO).encode(), b"<repo>")  # assembly.html's cad/ commands name it
    if path.suffix == ".3mf":
        with zipfile.ZipFile(path) as z:
            return b"".join(name.encode() + z.read(name) for name in sorted(z.namelist()))
    if path.suffix == ".dxf":
        # The header holds dates and GUIDs, and ezdxf orders its CLASSES section by a set.
        found = DXF_ENTITIES.search(data)
        return found.group(0) if found else data
    if path.suffix == ".step":
        return STEP_DATE.sub(rb"FILE_NAME('\1','-'", data)
    if path.name == "report.json":
        report = json.loads(data)
        report.pop("timings_s", None)
        report.pop("versions", None)  # the installed packages, not the code's behaviour
        report.get("run", {}).pop("date", None)
        return json.dumps(report, sort_keys=True).encode()
    if path.name == "manifest.json":
        # Its time and its files' hashes (of timings, dates) vary; each file has its own line.
        manifest = json.loads(data)
        manifest.pop("created_utc", None)
        manifest["files"] = sorted(manifest["files"])
        return json.dumps(manifest, sort_keys=True).encode()
    if path.suffix == ".html":
        text = TIMING_SECTION.sub("", data.decode())
        text = REPORT_DATE.sub('<span class="date">-</span>', text)
        return REPORT_DIGEST.sub("", text).encode()
    return data


#: Exit statuses after which every file is written: OK, and the report's verdict FAIL (5) or,
#: with --strict, WARN (6) (aperture_fab.cli's EXIT_REPORT_FAIL and EXIT_REPORT_WARN).
WRITTEN_EXITS = (0, 5, 6)


def run(args: list[str]) -> None:
    done = subprocess.run(args, stdout=subprocess.DEVNULL)
    if done.returncode not in WRITTEN_EXITS:
        raise subprocess.CalledProcessError(done.returncode, args)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--work", type=Path, required=True, help="empty folder for the runs")
    args = parser.parse_args()
    exe = str(Path(sys.executable).with_name("aperture-fab"))
    targets = args.work / "targets"
    subprocess.run([sys.executable, "examples/make_targets.py", "--out", str(targets)],
                   check=True, stdout=subprocess.DEVNULL)
    design = args.work / "design"
    run([exe, "design", str(targets / "digit-3.png"), "--out", str(design / "plate.stl"),
         *DESIGN_FLAGS])
    run([exe, "validate", str(design / "plate.stl"), "--config", str(design / "design.toml"),
         str(targets / "digit-3.png"), "--out", str(args.work / "validate"),
         "--tolerance-samples", "2", "--mesh-samples", "8", "--quiet"])
    run([exe, "render", str(design / "design.npz"), str(targets / "digit-3.png"),
         "--config", str(design / "design.toml"), "--eye", "0.5,-0.5",
         "--out", str(args.work / "render.png")])
    for path in sorted(p for p in args.work.rglob("*") if p.is_file()):
        if targets in path.parents:
            continue
        digest = hashlib.sha256(normalized(path, args.work)).hexdigest()
        print(f"{digest[:16]}  {path.relative_to(args.work)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
