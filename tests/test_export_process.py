"""A process that cannot make a design's plate (issue 21, item 3): `export` and `design` refuse it
with the design settings and the exact design command that make a plate it can.

export does not change the plate: the open fractions were optimized through the design's own
plate (its thickness clips oblique light at the hole walls; its cells are the design's grid),
so a plate of another thickness or pitch is a new design. rules.makeable_settings says which
settings; the CLI turns them into flags.
"""

from __future__ import annotations

import dataclasses
import re
import shlex
from collections.abc import Iterator
from pathlib import Path

import pytest
import torch

from aperture_fab.cli import EXIT_FAILED, EXIT_OK, main
from aperture_fab.config.config import resolve
from aperture_fab.fabrication.process import PROCESSES, UnmakeableError
from aperture_fab.fabrication.quantize import made_sizes
from aperture_fab.fabrication.rules import check_plate, makeable_settings
from aperture_fab.io.images import encode_png
from aperture_fab.optics.scene import Plate
from aperture_fab.targets import natural

pytestmark = pytest.mark.usefixtures("one_torch_thread")

#: What the default preset's photomask plate (0.005 mm, 0.5 mm cells, 40 x 40) needs per
#: process: the design flags the refusal names.
DEFAULT_FIXES = {
    "laser": ["--thickness-mm", "0.1"],
    "etched-foil": ["--thickness-mm", "0.025"],
    "fdm": ["--thickness-mm", "0.4", "--pitch-mm", "2.3", "--cells", "8", "8"],
    "resin": ["--thickness-mm", "0.2"],
}
#: The same for tests/conftest.py's tiny design (16 x 16 cells of 0.25 mm).
TINY_FIXES = {**DEFAULT_FIXES,
              "laser": ["--thickness-mm", "0.1", "--pitch-mm", "0.5", "--cells", "8", "8"],
              "fdm": [*DEFAULT_FIXES["fdm"][:4], "--cells", "1", "1"]}
#: A command in backticks in a message.
QUOTED = re.compile(r"`([^`]+)`")


def _plates() -> list[tuple[str, Plate]]:
    near_eye = resolve("near-eye").scene.plate
    return [("near-eye", near_eye),
            ("seed", resolve("seed").scene.plate),  # 0.2 mm, non-square cells, straight holes
            ("thick", dataclasses.replace(near_eye, thickness_mm=12.0)),
            ("fine", dataclasses.replace(near_eye, pitch_mm=(0.05, 0.05), cells=(400, 400)))]


#: The near-eye preset's eye relief, mm: the pupil to the plate's top face.
EYE_RELIEF_MM = 10.0


@pytest.mark.parametrize("process", list(PROCESSES))
@pytest.mark.parametrize(("name", "plate"), _plates())
def test_makeable_settings_give_a_plate_the_process_makes(process: str, name: str,
                                                          plate: Plate) -> None:
    """The settings pass check_plate and leave room for a made hole at the chief-ray top face;
    the grid stays within its former extent; nothing changes for a plate already makeable."""
    proc = PROCESSES[process]
    changes = makeable_settings(proc, plate, EYE_RELIEF_MM)
    new = dataclasses.replace(
        plate, thickness_mm=changes.get("plate.thickness_mm", plate.thickness_mm),
        pitch_mm=tuple(changes.get("plate.pitch_mm", plate.pitch_mm)),
        cells=tuple(changes.get("plate.cells", plate.cells)))
    check_plate(proc, new)
    made_sizes(new, proc, eye_distance_mm=EYE_RELIEF_MM + new.thickness_mm / 2)
    assert all(n <= old + 1e-9 for n, old in zip(new.size_mm, plate.size_mm, strict=True))
    try:
        check_plate(proc, plate, EYE_RELIEF_MM)
    except UnmakeableError as err:
        assert changes, f"{process} refuses {name} but makeable_settings changes nothing"
        assert f"{process} makes the plate designed with" in str(err)
    else:
        assert changes == {}


def test_no_room_at_a_chief_ray_top_face_is_refused_with_the_pitch() -> None:
    """At exactly the minimum pitch a tilted hole has no room at the top face: the process
    refuses (exit 1 from the CLI) naming the pitch, not a diffraction error about d_max_mm."""
    plate = Plate(cells=(50, 50), pitch_mm=(0.4, 0.4), gap_mm=10.0, thickness_mm=0.1,
                  hole_axis="chief_ray")
    check_plate(PROCESSES["laser"], plate)  # the mid-plane rule passes
    with pytest.raises(UnmakeableError, match=r"top face .* give plate\.pitch_mm above 0\.40"):
        made_sizes(plate, PROCESSES["laser"], eye_distance_mm=10.0)


def _quoted_command(message: str) -> list[str]:
    commands = [shlex.split(c) for c in QUOTED.findall(message) if c.startswith("aperture-fab ")]
    assert len(commands) == 1, message
    return commands[0]


def _flags_after(command: list[str], process: str) -> list[str]:
    """The flags after --process NAME and --out X (those the refusal adds)."""
    assert command[command.index("--process") + 1] == process
    return command[command.index("--out") + 2:]


def test_export_for_the_designs_process_writes_the_part(designed: Path, tmp_path: Path) -> None:
    out = tmp_path / "mask" / "plate.svg"
    assert main(["export", str(designed / "design.npz"), "--process", "photomask", "--out",
                 str(out), "--quiet"]) == EXIT_OK
    assert out.read_text().startswith("<?xml")


@pytest.mark.parametrize("process", ["laser", "etched-foil", "fdm", "resin"])
def test_export_names_the_design_command_for_a_process_that_refuses_the_plate(
        designed: Path, tmp_path: Path, process: str, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "part" / "plate.svg"
    assert main(["export", str(designed / "design.npz"), "--process", process, "--out",
                 str(out)]) == EXIT_FAILED
    assert not out.exists()
    message = capsys.readouterr().err
    assert message.startswith("aperture-fab: error: ") and message.count("\n") == 1
    assert f"outside the {process} range" in message
    assert "export cannot re-make them in another plate" in message
    assert "the image(s) the design was made for, in its order: marker" in message
    assert "--force" in message
    command = _quoted_command(message)
    assert command[:5] == ["aperture-fab", "design", "TARGET", "--config",
                           str(designed / "design.toml")]
    assert command[command.index("--out") + 1] == str(designed.with_name(
        f"{designed.name}-{process}"))
    assert _flags_after(command, process) == TINY_FIXES[process]


def test_design_refusal_repeats_the_command_with_the_flags(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from conftest import design_tiny

    assert design_tiny(tmp_path, "--process", "laser", "--out", str(tmp_path / "out")) == \
        EXIT_FAILED
    assert not (tmp_path / "out").exists()  # refused before any work
    command = _quoted_command(capsys.readouterr().err)
    assert command[:2] == ["aperture-fab", "design"] and "--process" in command
    assert command[-len(TINY_FIXES["laser"]):] == TINY_FIXES["laser"]


@pytest.fixture(scope="module")
def default_design(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Path]:
    """A design of the default preset (photomask film, 40 x 40 cells) after one iteration,
    not validated: what `aperture-fab design img.png` makes, fast."""
    folder = tmp_path_factory.mktemp("default") / "x"
    folder.parent.joinpath("img.png").write_bytes(encode_png(natural(128)))
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        assert main(["design", str(folder.parent / "img.png"), "--out", str(folder),
                     "--iterations", "1", "--no-validate", "--quiet"]) == EXIT_OK
        yield folder
    finally:
        torch.set_num_threads(threads)


@pytest.mark.slow
def test_default_design_exports_to_photomask_and_names_commands_for_the_rest(
        default_design: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """README's export example runs; laser and fdm's named design commands make a part with
    holes that export then writes for that process."""
    out = default_design.parent / "mask" / "plate.svg"
    assert main(["export", str(default_design / "design.npz"), "--process", "photomask",
                 "--out", str(out), "--quiet"]) == EXIT_OK
    capsys.readouterr()
    for process, fix in DEFAULT_FIXES.items():
        assert main(["export", str(default_design / "design.npz"), "--process", process,
                     "--out", str(default_design.parent / process)]) == EXIT_FAILED
        command = _quoted_command(capsys.readouterr().err)
        assert _flags_after(command, process) == fix
        if process not in ("laser", "fdm"):  # thickness only: the unit test covers it
            continue
        image = str(default_design.parent / "img.png")
        argv = [image if word == "TARGET" else word for word in command[1:]]
        assert main([*argv, "--iterations", "1", "--no-validate", "--quiet"]) == EXIT_OK
        made = Path(command[command.index("--out") + 1])
        assert main(["export", str(made / "design.npz"), "--out",
                     str(made / f"{process}.svg")]) == EXIT_OK
        holes = re.search(r"wrote (\d+) holes, process (\S+):", capsys.readouterr().out)
        assert holes is not None and holes.group(2) == process
        assert int(holes.group(1)) > 0, f"{process}: the suggested design made no holes"
