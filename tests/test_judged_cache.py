"""The judged cache: the regular family's judgements kept between runs under a digest of every
input (aperture_fab.validation.judged_cache, aperture_fab.pipeline.judged_folder)."""

from __future__ import annotations

import dataclasses
import logging
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import tiny_config

import aperture_fab.validation.regular as regular_module
from aperture_fab.fabrication.process import resolve_process
from aperture_fab.io.images import prepare_targets
from aperture_fab.optics.eyes import distribution_of
from aperture_fab.pipeline.judged_folder import ENV_CACHE_DIR, FolderCache, default_cache
from aperture_fab.targets import EXAMPLES
from aperture_fab.validation.judged_cache import MemoryCache, digest
from aperture_fab.validation.made_quality import MadeQuality, as_arrays, from_arrays
from aperture_fab.validation.regular import RegularArray, elemental, regular_arrays, regular_front

#: Arrays of the tiny scene's family to judge: a few lattices' worth.
ARRAYS = 6


def tiny_family():  # type: ignore[no-untyped-def]
    scene = tiny_config("near-eye").scene
    arrays = regular_arrays(scene, resolve_process("photomask"))[:ARRAYS]
    targets, _ = prepare_targets([EXAMPLES["digit-3"]()], scene.eye.view_pixels,
                                 scene.display.pixels)
    return scene, arrays, targets, distribution_of(scene.eye).evaluation_states(4)


def dimmed(regular: RegularArray, shown: np.ndarray) -> list[np.ndarray]:
    """A stand-in for a display fit: the elemental images, then at half their level."""
    return [shown, shown / 2]


def fronts_equal(a, b) -> None:  # type: ignore[no-untyped-def]
    for field in dataclasses.fields(a):
        np.testing.assert_array_equal(getattr(a, field.name), getattr(b, field.name))


def test_a_digest_is_of_the_content() -> None:
    a = np.arange(6.0).reshape(2, 3)
    assert digest(a, 1.0, "x") == digest(a.copy(), 1.0, "x")
    changed = a.copy()
    changed[1, 2] += 1e-12
    keys = {digest(a, 1.0, "x"), digest(changed, 1.0, "x"), digest(a.astype(np.float32), 1.0, "x"),
            digest(a.reshape(3, 2), 1.0, "x"), digest(a, 1, "x"), digest(a, 1.0, "y"),
            digest(torch.as_tensor(a), 1.0, "x")}
    assert len(keys) == 6  # a tensor digests as its array; every other change misses
    scene = tiny_config().scene
    assert digest(scene) == digest(dataclasses.replace(scene))
    assert digest(scene) != digest(dataclasses.replace(
        scene, plate=dataclasses.replace(scene.plate, gap_mm=scene.plate.gap_mm + 1e-9)))
    with pytest.raises(TypeError, match="cannot digest a object"):
        digest(object())


@pytest.mark.parametrize("fitted", [False, True])
def test_a_cached_front_is_the_judged_one_and_judges_nothing_again(fitted, monkeypatch) -> None:
    _, arrays, targets, states = tiny_family()
    fit, key = (dimmed, "dimmed") if fitted else (None, None)
    cache = MemoryCache()
    judged = regular_front(targets, arrays, states, fit=fit, eye_level=0.001,
                           dtype=torch.float64, cache=cache, fit_key=key)
    assert len(cache.kept) == len(arrays)
    assert all(len(from_arrays(kept) or []) == (2 if fitted else 1)
               for kept in cache.kept.values())

    def refuse(*args, **kwargs):  # type: ignore[no-untyped-def]
        raise AssertionError("judged again")

    monkeypatch.setattr(regular_module, "judge_made", refuse)
    again = regular_front(targets, arrays, states, fit=fit and refuse, eye_level=0.001,
                          dtype=torch.float64, cache=cache, fit_key=key)
    fronts_equal(again, judged)
    monkeypatch.undo()
    fronts_equal(regular_front(targets, arrays, states, fit=fit, eye_level=0.001,
                               dtype=torch.float64), judged)  # the same as without a cache


def test_another_input_misses() -> None:
    _, arrays, targets, states = tiny_family()
    cache = MemoryCache()
    regular_front(targets, arrays, states, dtype=torch.float64, cache=cache)
    regular_front(targets, arrays, states, seed=1, dtype=torch.float64, cache=cache)
    regular_front(targets, arrays, states.subset([0, 1]), dtype=torch.float64, cache=cache)
    regular_front(targets, arrays, states, fit=dimmed, dtype=torch.float64, cache=cache,
                  fit_key="dimmed")
    regular_front(targets, arrays, states, fit=dimmed, dtype=torch.float64, cache=cache,
                  fit_key="dimmed, other settings")
    assert len(cache.kept) == 5 * len(arrays)


def test_a_fit_with_a_cache_needs_its_key() -> None:
    _, arrays, targets, states = tiny_family()
    with pytest.raises(ValueError, match="needs fit_key"):
        regular_front(targets, arrays, states, fit=dimmed, cache=MemoryCache())


def quality(seed: int) -> MadeQuality:
    rng = np.random.default_rng(seed)
    return MadeQuality(rng.normal(20, 2, (2, 3, 4)), float(rng.random()), float(rng.random()))


def test_a_folder_keeps_judgements_whole(tmp_path: Path) -> None:
    cache = FolderCache(tmp_path / "judged")
    assert cache.get("ab" * 32) is None
    kept = [quality(0), quality(1)]
    cache.put("ab" * 32, as_arrays(kept))
    arrays = cache.get("ab" * 32)
    back = None if arrays is None else from_arrays(arrays)
    assert back is not None and len(back) == 2
    for a, b in zip(back, kept, strict=True):
        np.testing.assert_array_equal(a.psnr_db, b.psnr_db)
        assert (a.efficiency, a.eye_level) == (b.efficiency, b.eye_level)
    assert not list((tmp_path / "judged").rglob("*.tmp"))  # written atomically


@pytest.mark.parametrize("content", [b"", b"not a zip", b"PK\x03\x04 truncated"])
def test_an_unreadable_file_is_judged_again_and_replaced(tmp_path: Path, content: bytes) -> None:
    cache = FolderCache(tmp_path)
    key = "cd" * 32
    cache.put(key, as_arrays([quality(0)]))
    next(tmp_path.rglob("*.npz")).write_bytes(content)
    assert cache.get(key) is None
    cache.put(key, as_arrays([quality(1)]))
    back = cache.get(key)
    assert back is not None
    np.testing.assert_array_equal(back["psnr_db_0"], quality(1).psnr_db)


def test_a_folder_that_cannot_be_written_is_no_cache(tmp_path: Path, caplog) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("a file where the folder would be")
    cache = FolderCache(blocker / "judged")
    with caplog.at_level(logging.WARNING):
        cache.put("ef" * 32, as_arrays([quality(0)]))
        cache.put("01" * 32, as_arrays([quality(0)]))
    assert cache.get("ef" * 32) is None
    warned = [r for r in caplog.records if "cannot write" in r.getMessage()]
    assert len(warned) == 1 and ENV_CACHE_DIR in warned[0].getMessage()


def test_a_record_that_is_no_judgement_reads_as_none() -> None:
    assert from_arrays({"views": np.zeros(3)}) is None
    assert from_arrays(as_arrays([quality(2)])) is not None


def test_the_environment_names_the_folder(tmp_path: Path, monkeypatch) -> None:
    monkeypatch.setenv(ENV_CACHE_DIR, "off")
    assert default_cache() is None
    monkeypatch.setenv(ENV_CACHE_DIR, str(tmp_path / "mine"))
    cache = default_cache()
    assert cache is not None and cache.folder == tmp_path / "mine"
    monkeypatch.delenv(ENV_CACHE_DIR)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    cache = default_cache()
    assert cache is not None and cache.folder == tmp_path / "xdg" / "aperture-fab" / "judged"


def test_elemental_contents_come_from_the_array_alone() -> None:
    """Why the family's key need not hold the contents: they are the array's elemental images
    of the targets, the same from the same inputs."""
    _, arrays, targets, _ = tiny_family()
    t = torch.as_tensor(targets)
    np.testing.assert_array_equal(elemental(arrays[0], t), elemental(arrays[0], t))


@pytest.mark.slow
def test_validate_reads_what_the_design_kept(tmp_path: Path, monkeypatch) -> None:
    """A design's report keeps the family's judgements and the baselines'; `validate` of the
    written part reads them all back (no new file) and reports the same made-part block and
    the same baselines over the eye distribution."""
    import json

    from aperture_fab.cli import EXIT_OK, EXIT_REPORT_FAIL, main
    from aperture_fab.io.images import encode_png
    from aperture_fab.targets import digit

    folder = tmp_path / "judged"
    monkeypatch.setenv(ENV_CACHE_DIR, str(folder))
    target = tmp_path / "t.png"
    target.write_bytes(encode_png(digit("3")))
    small = ["--quiet", "--tolerance-samples", "2", "--mesh-samples", "8"]
    assert main(["design", str(target), "--out", str(tmp_path / "d" / "plate.stl"), "--cells",
                 "16", "16", "--pitch-mm", "0.25", "--view-pixels", "16", "16", "--iterations",
                 "2", "--device", "cpu", *small]) in (EXIT_OK, EXIT_REPORT_FAIL)
    kept = sorted(folder.rglob("*.npz"))
    assert kept
    assert main(["validate", str(tmp_path / "d" / "plate.stl"), str(target), "--out",
                 str(tmp_path / "v"), *small]) in (EXIT_OK, EXIT_REPORT_FAIL)
    assert sorted(folder.rglob("*.npz")) == kept
    designed, validated = (json.loads((tmp_path / name / "report.json").read_text())
                           for name in ("d", "v"))
    assert designed["made_part"]["regular"] == validated["made_part"]["regular"]
    for name in ("open", "regular_pinholes", "optimized"):
        assert (designed["eye_distribution"]["variants"][name]
                == validated["eye_distribution"]["variants"][name])
