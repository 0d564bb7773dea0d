"""The design job: `design` (values in, values out) and `run_design` (files in, files out)."""

from __future__ import annotations

import json
import math
import os
import stat
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
from conftest import interrupt_at_call
from PIL import Image

import aperture_fab.io.files as files_module
import aperture_fab.optimize.optimizer as optimize_module
import aperture_fab.pipeline.design_job as pipeline_module
from aperture_fab.config.config import Config, parse_toml, resolve
from aperture_fab.io.atomic import write_atomic
from aperture_fab.io.files import load_targets
from aperture_fab.io.images import TargetWarning, encode_png, linear_to_srgb, resample
from aperture_fab.optimize.optimizer import Interrupted
from aperture_fab.pipeline.design_job import DesignResult, design, run_design
from aperture_fab.targets import asymmetric_marker, checker, pixel_art

pytestmark = pytest.mark.usefixtures("one_torch_thread")

MakeConfig = Callable[..., Config]

VARIANTS = ("initial", "optimized", "open", "regular_pinholes")
NPZ_KEYS = {"open_fraction", "displays", "loss_history"}
#: 8-bit sRGB PNGs hold a value to half a step.
HALF_STEP = 0.5 / 255 + 1e-9


def closed_form_gain_mse(view: np.ndarray, target: np.ndarray) -> float:
    """min over g of mean((g view - target)^2), independent of the package."""
    v, t = view.ravel(), target.ravel()
    vv = float(v @ v)
    if vv == 0:
        return float(t @ t) / t.size
    return (float(t @ t) - float(v @ t) ** 2 / vv) / t.size


def srgb_samples(path: Path) -> np.ndarray:
    """A PNG's 8-bit samples as floats in [0, 1], (C, H, W)."""
    with Image.open(path) as im:
        samples = np.asarray(im, dtype=np.float64) / 255
    return samples[None] if samples.ndim == 2 else samples.transpose(2, 0, 1)


def tmp_files(folder: Path) -> list[Path]:
    return sorted(folder.glob(".*.tmp"))


# --- design: values in, values out -----------------------------------------------------------


def test_design_returns_views_and_metrics_of_every_variant(make_config: MakeConfig) -> None:
    config = make_config(**{"optimizer.precision": "float64"})
    result = design([asymmetric_marker(32)], config)
    assert isinstance(result, DesignResult)
    assert result.config == config
    assert result.names == ("target0",)
    assert result.targets.shape == (1, 1, 16, 16)
    assert set(result.views) == set(VARIANTS) == set(result.metrics)
    for variant in VARIANTS:
        view = result.views[variant]
        assert view.shape == (1, 1, 1, 16, 16)  # (T, positions, C, ny, nx)
        assert np.all(np.isfinite(view)) and view.max() > 0
        mse = result.metrics[variant]["mse"]
        # The metric is the gain-corrected MSE of the view at the nominal position.
        assert mse == pytest.approx([closed_form_gain_mse(view[0, 0], result.targets[0])],
                                    rel=1e-6)
        assert result.metrics[variant]["psnr_db"] == pytest.approx(
            [10 * math.log10(1 / mse[0])], rel=1e-9)
    # The initial view is the optimizer's start and the optimized view its end. The optimizer
    # samples the display stack once per pixel, the judgement twice (tests/test_optimize.py
    # holds the optimizer's loss to a render at its own sampling).
    initial = result.metrics["initial"]["mse"][0]
    assert initial == pytest.approx(result.design.loss_history[0], rel=0.1)
    assert result.metrics["optimized"]["mse"][0] < initial
    # Without a plate the eye cannot focus on the display: the open view is the worst.
    assert result.metrics["open"]["mse"][0] > result.metrics["optimized"]["mse"][0]


def test_grey_targets_run_one_channel_and_colour_three(make_config: MakeConfig) -> None:
    config = make_config(**{"optimizer.iterations": 2})
    grey = design([asymmetric_marker(32), checker(32, 4)], config)
    assert grey.targets.shape[1] == 1 and grey.design.displays.shape[1] == 1
    colour = design([pixel_art(32)], config)
    assert colour.targets.shape == (1, 3, 16, 16)
    assert colour.design.displays.shape == (1, 3, 32, 32)
    assert colour.views["optimized"].shape == (1, 1, 3, 16, 16)
    # One colour target makes every target colour.
    mixed = design([asymmetric_marker(32), pixel_art(32)], config)
    assert mixed.targets.shape == (2, 3, 16, 16)
    np.testing.assert_allclose(mixed.targets[0, 0], mixed.targets[0, 2])


def test_targets_are_resampled_onto_the_view_grid(make_config: MakeConfig) -> None:
    config = make_config(**{"optimizer.iterations": 1})
    image = checker(64, 4)  # 4 x 4 squares: 4 x 4 view pixels each on a 16 x 16 view
    result = design([image], config)
    np.testing.assert_allclose(result.targets[0], resample(image[:1], (16, 16)))
    np.testing.assert_array_equal(result.targets[0, 0, :4, :4], 1.0)
    np.testing.assert_array_equal(result.targets[0, 0, :4, 4:8], 0.0)


def test_several_targets_share_one_plate_with_a_display_each(make_config: MakeConfig) -> None:
    config = make_config(**{"optimizer.iterations": 3})
    result = design([asymmetric_marker(32), checker(32, 4), 1 - checker(32, 4)], config,
                    names=["f", "c", "inverse"])
    assert result.names == ("f", "c", "inverse")
    assert result.design.open_fraction.shape == (16, 16)
    assert result.design.displays.shape == (3, 1, 32, 32)
    assert result.views["optimized"].shape == (3, 1, 1, 16, 16)
    for variant in VARIANTS:
        assert len(result.metrics[variant]["mse"]) == 3
        assert len(result.metrics[variant]["psnr_db"]) == 3
    # The checker and its inverse give different displays and different views.
    assert np.abs(result.design.displays[1] - result.design.displays[2]).max() > 0.5
    assert result.metrics["optimized"]["mse"][1] != result.metrics["optimized"]["mse"][2]


def test_design_needs_a_target(make_config: MakeConfig) -> None:
    with pytest.raises(ValueError, match="no targets"):
        design([], make_config())


# --- write_atomic ----------------------------------------------------------------------------


def test_write_atomic_writes_bytes_and_text(tmp_path: Path) -> None:
    write_atomic(tmp_path / "a.bin", b"\x00\x01\xff")
    write_atomic(tmp_path / "b.txt", "grüße\n")
    write_atomic(tmp_path / "b.txt", "replaced")
    assert (tmp_path / "a.bin").read_bytes() == b"\x00\x01\xff"
    assert (tmp_path / "b.txt").read_text(encoding="utf-8") == "replaced"
    assert tmp_files(tmp_path) == []


@pytest.mark.parametrize("failing", ["replace", "fsync"])
def test_write_atomic_keeps_the_old_file_when_writing_fails(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, failing: str) -> None:
    path = tmp_path / "design.json"
    path.write_text("old")

    def fail(*args: Any, **kwargs: Any) -> None:
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(files_module.os, failing, fail)
    with pytest.raises(OSError, match="No space left"):
        write_atomic(path, "new " * 1000)
    monkeypatch.undo()
    assert path.read_text() == "old"
    assert tmp_files(tmp_path) == []
    assert sorted(p.name for p in tmp_path.iterdir()) == ["design.json"]


def test_write_atomic_keeps_the_old_file_on_ctrl_c(tmp_path: Path,
                                                    monkeypatch: pytest.MonkeyPatch) -> None:
    path = tmp_path / "design.npz"
    path.write_bytes(b"old")

    def interrupt(*args: Any) -> None:
        raise KeyboardInterrupt

    monkeypatch.setattr(files_module.os, "fsync", interrupt)
    with pytest.raises(KeyboardInterrupt):
        write_atomic(path, b"new")
    monkeypatch.undo()
    assert path.read_bytes() == b"old"
    assert tmp_files(tmp_path) == []


def test_write_atomic_gives_files_the_usual_permissions(tmp_path: Path) -> None:
    # Not mkstemp's private 0600: outputs are as readable as any file the user writes.
    plain = tmp_path / "plain.txt"
    plain.write_text("x")  # mode 0666 less the umask
    write_atomic(tmp_path / "atomic.txt", "x")
    mode = stat.S_IMODE((tmp_path / "atomic.txt").stat().st_mode)
    assert mode == stat.S_IMODE(plain.stat().st_mode)


# --- run_design: files -----------------------------------------------------------------------


def test_run_design_writes_every_output(tmp_path: Path, make_config: MakeConfig,
                                        monkeypatch: pytest.MonkeyPatch) -> None:
    # A non-square display and view, so swapped axes show; a colour target.
    config = make_config(**{"display.width_mm": 4.0, "display.height_mm": 3.0,
                            "display.pixels": [32, 24], "eye.view_pixels": [16, 12],
                            "optimizer.checkpoint_every": 2})
    target = tmp_path / "pixel art.png"
    target.write_bytes(encode_png(pixel_art(32)))
    checkpoints: list[Path] = []
    real_save = pipeline_module.save_checkpoint

    def save(folder: Path, state: dict[str, Any], fingerprint: str) -> None:
        real_save(folder, state, fingerprint)
        checkpoints.append(folder / "checkpoint.pt")
        assert (folder / "checkpoint.pt").is_file()

    monkeypatch.setattr(pipeline_module, "save_checkpoint", save)
    with pytest.warns(TargetWarning, match="stretched"):  # a square target, a 4:3 display
        result = run_design([target], tmp_path / "out" / "plate.stl", config, progress=False)
    folder = tmp_path / "out"
    name = "pixel_art"  # the file stem, made safe for file names
    assert result.names == (name,)

    # Checkpoints were written along the way and removed once the run completed.
    assert len(checkpoints) == 8 // 2
    assert not (folder / "checkpoint.pt").exists()
    assert tmp_files(folder) == []
    assert not (folder / "plate.stl").exists()  # the part itself is another stage's

    with np.load(folder / "design.npz") as npz:
        assert NPZ_KEYS <= set(npz.files)
        np.testing.assert_array_equal(npz["open_fraction"], result.design.open_fraction)
        np.testing.assert_array_equal(npz["displays"], result.design.displays)
        np.testing.assert_array_equal(npz["loss_history"], result.design.loss_history)
        assert npz["open_fraction"].shape == (16, 16)
        assert npz["displays"].shape == (1, 3, 24, 32)
        assert npz["loss_history"].shape == (8,)

    again = resolve(file_dict=parse_toml((folder / "design.toml").read_text(), "design.toml"))
    assert again == config

    summary = json.loads((folder / "design.json").read_text())
    assert summary["final_loss"] == pytest.approx(result.design.loss_history[-1], rel=1e-12)
    assert summary["iterations"] == 8
    assert summary["targets"] == [name]
    assert set(summary["metrics"]) == set(VARIANTS)
    for variant in VARIANTS:
        assert summary["metrics"][variant]["psnr_db"] == pytest.approx(
            result.metrics[variant]["psnr_db"], rel=1e-12)
    assert summary["config"]["display"]["pixels"] == [32, 24]

    # The display image at the display's resolution, holding the optimized content.
    display_png = folder / f"display_{name}.png"
    with Image.open(display_png) as im:
        assert im.size == (32, 24) and im.mode == "RGB"
    np.testing.assert_allclose(srgb_samples(display_png),
                               linear_to_srgb(result.design.displays[0]), atol=HALF_STEP)
    for variant in VARIANTS:
        with Image.open(folder / f"view_{variant}_{name}.png") as im:
            assert im.size == (16, 12)
    with Image.open(folder / f"target_{name}.png") as im:
        assert im.size == (16, 12)
    with Image.open(folder / "loss.png") as im:
        im.verify()


def test_run_design_writes_grey_pngs_for_grey_targets(tmp_path: Path, marker_png: Path,
                                                      make_config: MakeConfig) -> None:
    config = make_config(**{"optimizer.iterations": 2})
    result = run_design([marker_png], tmp_path / "out", config, progress=False)
    with Image.open(tmp_path / "out" / "display_marker.png") as im:
        assert im.mode == "L" and im.size == (32, 32)
    # The optimized view is saved scaled by its best gain, so it is comparable to the target.
    view = result.views["optimized"][0, 0]
    gain = float((view * result.targets[0]).sum() / (view * view).sum())
    saved = srgb_samples(tmp_path / "out" / "view_optimized_marker.png")
    np.testing.assert_allclose(saved, linear_to_srgb(np.clip(gain * view, 0, 1)), atol=HALF_STEP)


def test_targets_with_the_same_stem_get_distinct_names(tmp_path: Path,
                                                       make_config: MakeConfig) -> None:
    paths = []
    for sub, image in (("a", asymmetric_marker(32)), ("b", checker(32))):
        (tmp_path / sub).mkdir()
        paths.append(tmp_path / sub / "target.png")
        paths[-1].write_bytes(encode_png(image))
    result = run_design(paths, tmp_path / "out", make_config(**{"optimizer.iterations": 1}),
                        progress=False)
    assert len(set(result.names)) == 2
    for name in result.names:
        assert (tmp_path / "out" / f"display_{name}.png").is_file()


# --- the output folder -----------------------------------------------------------------------


@pytest.mark.parametrize(("out", "folder"), [
    ("parts/plate.stl", "parts"),
    ("parts/PLATE.STEP", "parts"),
    ("parts/plate.3mf", "parts"),
    ("deep/er/folder", "deep/er/folder"),
    ("folder.v2", "folder.v2"),
])
def test_outputs_go_in_the_folder_or_beside_the_part(tmp_path: Path, marker_png: Path,
                                                     make_config: MakeConfig, out: str,
                                                     folder: str) -> None:
    run_design([marker_png], tmp_path / out, make_config(**{"optimizer.iterations": 1}),
               progress=False)
    assert (tmp_path / folder / "design.npz").is_file()
    assert (tmp_path / folder / "design.toml").is_file()


def test_an_output_path_under_a_regular_file_is_refused(tmp_path: Path, marker_png: Path,
                                                        make_config: MakeConfig) -> None:
    blocker = tmp_path / "blocker"
    blocker.write_text("a file, not a folder")
    for out in (blocker / "plate.stl", blocker / "sub" / "plate.stl", blocker):
        with pytest.raises(ValueError, match=r"output folder .*blocker.*--out"):
            run_design([marker_png], out, make_config(), progress=False)
    assert blocker.read_text() == "a file, not a folder"


def test_a_folder_without_write_access_is_refused(tmp_path: Path, marker_png: Path,
                                                 make_config: MakeConfig,
                                                 monkeypatch: pytest.MonkeyPatch) -> None:
    # The same check as below, where root would be allowed anyway.
    monkeypatch.setattr(files_module.os, "access", lambda path, mode: False)
    with pytest.raises(ValueError, match=r"output folder .*out is not writable; choose another"):
        run_design([marker_png], tmp_path / "out" / "plate.stl", make_config(), progress=False)


@pytest.mark.skipif(not hasattr(os, "geteuid") or os.geteuid() == 0,
                    reason="root ignores folder permissions")
def test_an_unwritable_output_folder_is_refused(tmp_path: Path, marker_png: Path,
                                                make_config: MakeConfig) -> None:
    locked = tmp_path / "locked"
    locked.mkdir()
    locked.chmod(0o500)
    try:
        with pytest.raises(ValueError, match=r"locked.*not writable"):
            run_design([marker_png], locked / "plate.stl", make_config(), progress=False)
        with pytest.raises(ValueError, match="locked"):
            run_design([marker_png], locked / "new" / "plate.stl", make_config(),
                       progress=False)
    finally:
        locked.chmod(0o700)


# --- interruption and resume -----------------------------------------------------------------


@pytest.fixture
def resumable(make_config: MakeConfig) -> Config:
    return make_config(**{"optimizer.iterations": 10, "optimizer.checkpoint_every": 3,
                          "optimizer.precision": "float64"})


def npz_arrays(path: Path) -> dict[str, np.ndarray]:
    with np.load(path) as npz:
        return {key: npz[key] for key in NPZ_KEYS}


def test_an_interrupted_run_resumes_to_the_uninterrupted_result(
        tmp_path: Path, marker_png: Path, resumable: Config,
        monkeypatch: pytest.MonkeyPatch) -> None:
    run_design([marker_png], tmp_path / "whole", resumable, progress=False)
    out = tmp_path / "split"
    interrupt_at_call(monkeypatch, 5)  # after a checkpoint at 3, before the one at 6
    with pytest.raises(Interrupted) as info:
        run_design([marker_png], out, resumable, progress=False)
    monkeypatch.undo()
    assert info.value.state["iteration"] == 4
    assert (out / "checkpoint.pt").is_file()
    assert not (out / "design.npz").exists()
    saved = torch.load(out / "checkpoint.pt", weights_only=True)
    assert saved["state"]["iteration"] == 4  # the interruption's state, not the last checkpoint
    assert tmp_files(out) == []

    calls = {"n": 0}
    real = optimize_module.gain_mse_states

    def counted(view: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        calls["n"] += 1
        return real(view, target)

    monkeypatch.setattr(optimize_module, "gain_mse_states", counted)
    result = run_design([marker_png], out, resumable, resume=True, progress=False)
    assert calls["n"] == 10 - 4  # it went on from the checkpoint, not from the start
    assert result.design.loss_history.shape == (10,)
    assert not (out / "checkpoint.pt").exists()
    whole, split = npz_arrays(tmp_path / "whole" / "design.npz"), npz_arrays(out / "design.npz")
    for key in NPZ_KEYS:
        np.testing.assert_allclose(split[key], whole[key], rtol=1e-6, atol=1e-9, err_msg=key)
    summary = json.loads((out / "design.json").read_text())
    assert summary["iterations"] == 10


def test_resume_without_a_checkpoint_is_refused(tmp_path: Path, marker_png: Path,
                                                resumable: Config) -> None:
    with pytest.raises(ValueError, match=r"--resume: no checkpoint at .*checkpoint\.pt"):
        run_design([marker_png], tmp_path / "out", resumable, resume=True, progress=False)


def interrupted_folder(tmp_path: Path, marker_png: Path, config: Config,
                       monkeypatch: pytest.MonkeyPatch) -> Path:
    out = tmp_path / "out"
    interrupt_at_call(monkeypatch, 5)
    with pytest.raises(Interrupted):
        run_design([marker_png], out, config, progress=False)
    monkeypatch.undo()
    return out


def test_resume_with_another_config_is_refused(tmp_path: Path, marker_png: Path,
                                               resumable: Config, make_config: MakeConfig,
                                               monkeypatch: pytest.MonkeyPatch) -> None:
    out = interrupted_folder(tmp_path, marker_png, resumable, monkeypatch)
    other = make_config(**{"optimizer.iterations": 10, "optimizer.checkpoint_every": 3,
                           "optimizer.precision": "float64", "plate.gap_mm": 9.0})
    with pytest.raises(ValueError, match=r"the config .* changed"):
        run_design([marker_png], out, other, resume=True, progress=False)
    assert (out / "checkpoint.pt").is_file()  # still there for the right config
    run_design([marker_png], out, resumable, resume=True, progress=False)


def test_resume_with_other_targets_is_refused(tmp_path: Path, marker_png: Path,
                                              resumable: Config,
                                              monkeypatch: pytest.MonkeyPatch) -> None:
    out = interrupted_folder(tmp_path, marker_png, resumable, monkeypatch)
    other = tmp_path / "other.png"
    other.write_bytes(encode_png(checker(32)))
    with pytest.raises(ValueError, match=r"target image 1 .* changed"):
        run_design([other], out, resumable, resume=True, progress=False)


def test_a_refused_resume_keeps_the_interrupted_runs_config(
        tmp_path: Path, marker_png: Path, resumable: Config, make_config: MakeConfig,
        monkeypatch: pytest.MonkeyPatch) -> None:
    out = interrupted_folder(tmp_path, marker_png, resumable, monkeypatch)
    other = make_config(**{"plate.gap_mm": 9.0})
    with pytest.raises(ValueError):
        run_design([marker_png], out, other, resume=True, progress=False)
    # Neither run published anything: the folder holds the checkpoint alone, for --resume.
    assert sorted(p.name for p in out.iterdir()) == ["checkpoint.pt"]


# --- bad target files ------------------------------------------------------------------------


def truncated_png() -> bytes:
    data = encode_png(asymmetric_marker(32))
    return data[: len(data) // 2]


@pytest.mark.parametrize(("content", "message"), [
    (None, "does not exist"),
    (b"", "empty"),
    (b"this is not an image at all" * 10, None),
    (truncated_png(), "truncated"),
    ("folder", "folder"),
])
def test_bad_target_files_are_refused_by_name(
        tmp_path: Path, make_config: MakeConfig, content: bytes | str | None,
        message: str | None) -> None:
    path = tmp_path / "bad target.png"
    if content == "folder":
        path.mkdir()
    elif isinstance(content, bytes):
        path.write_bytes(content)
    with pytest.raises(ValueError, match=message) as info:
        run_design([path], tmp_path / "out", make_config(), progress=False)
    assert str(path) in str(info.value)
    assert not (tmp_path / "out" / "design.npz").exists()


def test_load_targets_reads_linear_images_and_names_them(tmp_path: Path) -> None:
    paths = [tmp_path / "F.png", tmp_path / "sub dir.png"]
    paths[0].write_bytes(encode_png(asymmetric_marker(32)))
    image = np.full((3, 8, 8), 0.25)
    paths[1].write_bytes(encode_png(image))
    images, names = load_targets(paths)
    assert names == ["F", "sub_dir"]
    np.testing.assert_allclose(images[0], asymmetric_marker(32), atol=1e-9)
    # sRGB in the file, linear light in memory: 0.25 linear survives to 8-bit precision.
    np.testing.assert_allclose(images[1], 0.25, rtol=0.01)
