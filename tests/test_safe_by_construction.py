"""Safe by construction (issue 21, item 11): a checkpoint is data and is read as data (one that
would run code is refused, never run), an output folder loses only the files its own manifest
lists (the user's files stay, whatever their names), and two runs publishing into one folder
take turns."""

from __future__ import annotations

import io
import json
import pickle
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch

import aperture_fab.io.manifest as manifest_module
from aperture_fab.config.config import Config
from aperture_fab.fabrication.process import PROCESSES
from aperture_fab.fabrication.quantize import made_sizes
from aperture_fab.io.images import encode_png, resample
from aperture_fab.io.manifest import (
    LOCK_NAME,
    MANIFEST_NAME,
    check_folder,
    file_sha256,
    publish,
    staging,
)
from aperture_fab.optimize.optimizer import EYE_FLOOR_MEMORY, MaskDesign, optimize
from aperture_fab.pipeline.checkpoint import (
    CHECKPOINT_NAME,
    CHECKPOINT_VERSION,
    input_digests,
    resume_state,
    save_checkpoint,
)
from aperture_fab.pipeline.design_job import run_design
from aperture_fab.sweep.worker import POINT_FILE, clear_attempt
from aperture_fab.targets import asymmetric_marker, checker

pytestmark = pytest.mark.usefixtures("one_torch_thread")

MakeConfig = Callable[..., Config]
COMMAND = ("aperture-fab", "test")


# --- checkpoints hold data only ---------------------------------------------------------------


class Hostile:
    """Unpickling it creates `marker`: what a checkpoint from someone else could do."""

    def __init__(self, marker: Path) -> None:
        self.marker = str(marker)

    def __reduce__(self) -> tuple[Any, tuple[str, str]]:
        return open, (self.marker, "w")


def hostile_raw(marker: Path) -> bytes:
    return pickle.dumps({"state": Hostile(marker), "inputs": {}})


def hostile_torch(marker: Path) -> bytes:
    """torch.save's zip format, the object inside a checkpoint-shaped dict."""
    buffer = io.BytesIO()
    torch.save({"format": "aperture-fab checkpoint", "version": CHECKPOINT_VERSION,
                "state": {"iteration": Hostile(marker)}, "inputs": {}}, buffer)
    return buffer.getvalue()


@pytest.mark.parametrize("make", [hostile_raw, hostile_torch])
def test_a_hostile_checkpoint_is_refused_and_never_run(
        tmp_path: Path, marker_png: Path, make_config: MakeConfig,
        make: Callable[[Path], bytes]) -> None:
    # The payload is live: plain unpickling runs it.
    control = tmp_path / "control"
    pickle.loads(hostile_raw(control))
    assert control.exists()

    marker = tmp_path / "pwned"
    out = tmp_path / "out"
    out.mkdir()
    (out / CHECKPOINT_NAME).write_bytes(make(marker))
    with pytest.raises(ValueError) as info:
        run_design([marker_png], out, make_config(), resume=True, progress=False)
    message = str(info.value)
    assert str(out / CHECKPOINT_NAME) in message
    assert "Delete it and run without --resume" in message
    assert "weights_only" not in message  # torch's advice to load it unsafely is not passed on
    assert not marker.exists()
    assert sorted(p.name for p in out.iterdir()) == [CHECKPOINT_NAME]  # nothing else happened


def test_a_checkpoint_of_the_old_format_is_refused(tmp_path: Path, marker_png: Path,
                                                   make_config: MakeConfig) -> None:
    out = tmp_path / "out"
    out.mkdir()
    torch.save({"state": {"iteration": 3}, "inputs": {}}, out / CHECKPOINT_NAME)  # no format
    with pytest.raises(ValueError, match=r"checkpoint\.pt is not an aperture-fab checkpoint of "
                       r"this version .* Delete it and run without --resume"):
        run_design([marker_png], out, make_config(), resume=True, progress=False)


def test_a_checkpoint_missing_state_is_refused_by_name(tmp_path: Path) -> None:
    buffer = io.BytesIO()
    torch.save({"format": "aperture-fab checkpoint", "version": CHECKPOINT_VERSION,
                "state": {"iteration": 3}, "inputs": {}}, buffer)
    (tmp_path / CHECKPOINT_NAME).write_bytes(buffer.getvalue())
    with pytest.raises(ValueError, match=r"lacks state\['history'\], .*Delete it"):
        resume_state(tmp_path / CHECKPOINT_NAME, {}, [])


def test_only_data_is_saved(tmp_path: Path) -> None:
    with pytest.raises(TypeError, match=r"checkpoint\['state'\]\['best'\] is a ndarray"):
        save_checkpoint(tmp_path, {"best": np.zeros(2)}, {})
    assert not (tmp_path / CHECKPOINT_NAME).exists()


def optimize_marker(config: Config, **kwargs: Any) -> MaskDesign:
    scene = config.scene
    image = asymmetric_marker(32)[:1]
    targets = resample(image, scene.eye.view_pixels)[None]
    shown = resample(image, scene.display.pixels)[None]
    return optimize(scene, targets, shown, config.optimizer, progress=False, **kwargs)


@pytest.mark.parametrize(("method", "eye_floor"), [("adam", 0.0), ("sgd", 0.0), ("adam", 0.0003)])
def test_a_checkpoint_file_resumes_to_the_same_result(tmp_path: Path, marker_png: Path,
                                                      make_config: MakeConfig,
                                                      method: str, eye_floor: float) -> None:
    """Saved to checkpoint.pt and read back, a state resumes exactly as the state in memory:
    the optimizer's moments, the history, the design kept before the snap (a tuple) and, with
    a floor on the light at the eye, the steps since the view was last below it."""
    config = make_config(**{"plate.thickness_mm": 0.3, "optimizer.iterations": 12,
                            "optimizer.checkpoint_every": 4, "optimizer.precision": "float64",
                            "optimizer.quantize_share": 0.5, "optimizer.method": method,
                            "optimizer.min_eye_level": eye_floor})
    made = made_sizes(config.scene.plate, PROCESSES["resin"], config.scene.mid_plane_distance_mm)
    saved: list[dict[str, Any]] = []
    whole = optimize_marker(config, made=made, on_checkpoint=saved.append)
    state = saved[1]  # iteration 8: after the snap at 6, so it holds the continuous design
    assert state["iteration"] == 8 and isinstance(state["continuous"], tuple)
    # with the floor, the view was below it at iteration 8: the hold's count must resume too
    assert (state["since_below_floor"] <= EYE_FLOOR_MEMORY) == (eye_floor > 0)
    inputs = input_digests([marker_png], config, None)
    save_checkpoint(tmp_path, state, inputs)
    loaded = resume_state(tmp_path / CHECKPOINT_NAME, inputs, [marker_png])
    assert isinstance(loaded["continuous"], tuple)
    from_file = optimize_marker(config, made=made, state=loaded)
    from_memory = optimize_marker(config, made=made, state=state)
    np.testing.assert_array_equal(from_file.loss_history, from_memory.loss_history)
    np.testing.assert_array_equal(from_file.open_fraction, from_memory.open_fraction)
    np.testing.assert_array_equal(from_file.displays, from_memory.displays)
    assert from_file.continuous is not None and from_memory.continuous is not None
    for got, want in zip(from_file.continuous, from_memory.continuous, strict=True):
        np.testing.assert_array_equal(got, want)
    np.testing.assert_allclose(from_file.loss_history, whole.loss_history, rtol=1e-6)
    np.testing.assert_array_equal(from_file.open_fraction, whole.open_fraction)


# --- the tool deletes only what its manifest lists --------------------------------------------


def publish_files(folder: Path, files: dict[str, bytes], **kwargs: Any) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    with staging(folder) as stage:
        for name, data in files.items():
            (stage / name).write_bytes(data)
        publish(stage, folder, COMMAND, **kwargs)


def test_a_design_keeps_the_users_files_and_removes_only_its_stale_ones(
        tmp_path: Path, make_config: MakeConfig) -> None:
    out = tmp_path / "out"
    out.mkdir()
    own = out / "mytarget.png"  # a target the user keeps in the output folder
    own.write_bytes(encode_png(asymmetric_marker(32)))
    holiday = out / "view_holiday.png"  # named like the views the tool writes
    holiday.write_bytes(b"the user's photo")
    config = make_config(**{"optimizer.iterations": 2})
    run_design([own], out, config, progress=False)
    first = json.loads((out / MANIFEST_NAME).read_text())["files"]
    assert "view_optimized_mytarget.png" in first
    assert own.name not in first and holiday.name not in first

    other = tmp_path / "other.png"
    other.write_bytes(encode_png(checker(32)))
    edited = out / "target_mytarget.png"  # listed, then changed by the user: theirs now
    edited.write_bytes(b"the user's edit")
    run_design([other], out, config, progress=False)
    files = json.loads((out / MANIFEST_NAME).read_text())["files"]
    names = {p.name for p in out.iterdir()}
    assert names == set(files) | {MANIFEST_NAME, own.name, holiday.name, edited.name}
    stale = {name for name in first if name.endswith("_mytarget.png")} - {edited.name}
    assert stale and not stale & names  # the earlier run's views went
    assert own.read_bytes() == encode_png(asymmetric_marker(32))
    assert holiday.read_bytes() == b"the user's photo"
    assert edited.read_bytes() == b"the user's edit"
    check_folder(out)


def test_a_publish_without_a_manifest_removes_nothing(tmp_path: Path) -> None:
    folder = tmp_path / "out"
    folder.mkdir()
    for name in ("design.npz", "report.html", "view_initial_x.png"):  # an older run's, unlisted
        (folder / name).write_bytes(b"old")
    publish_files(folder, {"design.npz": b"new", "plate.stl": b"solid"})
    assert (folder / "design.npz").read_bytes() == b"new"  # a name this run writes is replaced
    assert (folder / "report.html").read_bytes() == b"old"
    assert (folder / "view_initial_x.png").read_bytes() == b"old"
    check_folder(folder)


def test_a_manifest_naming_files_outside_the_folder_removes_nothing_there(tmp_path: Path
                                                                           ) -> None:
    folder = tmp_path / "out"
    publish_files(folder, {"a.txt": b"a"})
    outside = tmp_path / "precious.txt"
    outside.write_bytes(b"keep")
    manifest = json.loads((folder / MANIFEST_NAME).read_text())
    manifest["files"]["../precious.txt"] = {"sha256": file_sha256(outside), "size_bytes": 4}
    (folder / MANIFEST_NAME).write_text(json.dumps(manifest))
    publish_files(folder, {"b.txt": b"b"})
    assert outside.read_bytes() == b"keep"
    assert not (folder / "a.txt").exists()


def test_a_publish_killed_midway_is_cleaned_up_by_the_next(tmp_path: Path,
                                                           monkeypatch: pytest.MonkeyPatch
                                                           ) -> None:
    folder = tmp_path / "out"
    publish_files(folder, {"a.txt": b"a", "shared.txt": b"1"})
    (folder / "notes.txt").write_text("mine")

    def killed(*_args: Any) -> None:
        raise KeyboardInterrupt

    monkeypatch.setattr(manifest_module, "_remove", killed)  # after the renames, before removal
    with pytest.raises(KeyboardInterrupt):
        publish_files(folder, {"shared.txt": b"2", "c.txt": b"c"})
    monkeypatch.undo()
    with pytest.raises(ValueError, match="stopped while publishing"):
        check_folder(folder)
    publish_files(folder, {"d.txt": b"d"})
    assert sorted(p.name for p in folder.iterdir()) == ["d.txt", MANIFEST_NAME, "notes.txt"]
    check_folder(folder)


def test_a_retried_sweep_point_removes_only_the_attempts_files(tmp_path: Path) -> None:
    folder = tmp_path / "points" / "p1"
    publish_files(folder, {"report.json": b"{}", "plate.stl": b"solid"})
    for name in (POINT_FILE, CHECKPOINT_NAME, "notes.txt", "view_holiday.png"):
        (folder / name).write_bytes(b"x")
    clear_attempt(folder)
    assert sorted(p.name for p in folder.iterdir()) == ["notes.txt", "view_holiday.png"]


# --- two runs publishing into one folder take turns -------------------------------------------


def test_a_publish_waits_for_the_lock_then_refuses_naming_the_folder(tmp_path: Path) -> None:
    folder = tmp_path / "out"
    publish_files(folder, {"a.txt": b"a"})
    before = {p.name: p.read_bytes() for p in folder.iterdir()}
    with manifest_module._publish_lock(folder, 0.0):
        with pytest.raises(ValueError, match=rf"output folder {folder}: another aperture-fab "
                           r"run is publishing into it .*give another --out"):
            publish_files(folder, {"b.txt": b"b"}, wait_s=0.2)
    assert not (folder / LOCK_NAME).exists()  # its holder removes it
    assert {p.name: p.read_bytes() for p in folder.iterdir()} == before
    publish_files(folder, {"b.txt": b"b"})
    assert sorted(p.name for p in folder.iterdir()) == ["b.txt", MANIFEST_NAME]


def test_concurrent_publishes_leave_one_whole_set(tmp_path: Path) -> None:
    folder = tmp_path / "out"
    folder.mkdir()
    sets = {run: {f"{run}_{i}.txt": f"{run} {i}".encode() for i in range(20)} | {
        "shared.txt": run.encode()} for run in ("first", "second")}
    errors: list[BaseException] = []

    def publisher(run: str) -> None:
        try:
            for _ in range(15):
                publish_files(folder, sets[run])
        except BaseException as err:  # reported below, in the test's thread
            errors.append(err)

    threads = [threading.Thread(target=publisher, args=(run,)) for run in sets]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert not errors
    check_folder(folder)
    files = json.loads((folder / MANIFEST_NAME).read_text())["files"]
    assert set(files) in [set(s) for s in sets.values()]
    assert {p.name for p in folder.iterdir()} == set(files) | {MANIFEST_NAME}
