"""A design's checkpoint: the optimizer state saved while it runs (data only, never a pickle of
objects), and the digests of the inputs it was made with, so that --resume continues only the
same design."""

from __future__ import annotations

import hashlib
import io
import pickle
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch

from aperture_fab.config.config import Config
from aperture_fab.config.stages import FabricationSettings
from aperture_fab.config.written import to_toml
from aperture_fab.io.atomic import write_atomic

__all__ = ["CHECKPOINT_NAME", "input_digests", "load_checkpoint", "resume_state",
           "save_checkpoint", "sha256"]


CHECKPOINT_NAME = "checkpoint.pt"


#: The checkpoint format: torch.save of data only (tensors, numbers, strings, None, lists,
#: tuples, dicts), read back with weights_only=True. Version 1 had no marker and was read with
#: the full unpickler, so a checkpoint could run code: those are refused, not read.
CHECKPOINT_FORMAT = "aperture-fab checkpoint"


CHECKPOINT_VERSION = 3


CHECKPOINT_SCALARS = (str, bool, int, float)


#: The optimizer state a checkpoint must hold (key: allowed types), checked before resuming.
CHECKPOINT_STATE: dict[str, type | tuple[type, ...]] = {
    "iteration": int, "history": list, "best": float, "best_iteration": int,
    "mask_logits": torch.Tensor, "display": (torch.Tensor, type(None)),
    "optimizer": (dict, type(None)), "snap_from": int, "continuous": (tuple, type(None)),
    "since_below_floor": float,
}


def _check_data(value: Any, where: str) -> None:
    """Refuse (TypeError) a checkpoint value that is not plain data: what is saved must load
    with torch.load(weights_only=True), or the resume would be refused hours later."""
    if isinstance(value, dict):
        for key, item in value.items():
            _check_data(key, where)
            _check_data(item, f"{where}[{key!r}]")
    elif isinstance(value, (list, tuple)):
        for index, item in enumerate(value):
            _check_data(item, f"{where}[{index}]")
    elif not isinstance(value, (torch.Tensor, *CHECKPOINT_SCALARS)) and value is not None:
        raise TypeError(f"checkpoint value {where} is a {type(value).__name__}; a checkpoint "
                        "holds only tensors, numbers, strings, None and lists, tuples and "
                        "dicts of them (convert it before saving).")


def save_checkpoint(folder: Path, state: dict[str, Any], inputs: dict[str, str]) -> None:
    saved = {"format": CHECKPOINT_FORMAT, "version": CHECKPOINT_VERSION, "state": state,
             "inputs": inputs}
    _check_data(saved, "checkpoint")
    buffer = io.BytesIO()
    torch.save(saved, buffer)
    write_atomic(folder / CHECKPOINT_NAME, buffer.getvalue())


def sha256(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def input_digests(paths: Sequence[Path], config: Config, fabrication: FabricationSettings | None
                  ) -> dict[str, str]:
    """SHA-256 of every input of a design, by the name a message gives it: the resolved
    config, the fabrication process (it bounds the optimizer) and each target image's bytes."""
    digests = {"the config (--config file, preset and flags)": sha256(to_toml(config).encode())}
    if fabrication is not None:
        digests["the fabrication process (--process, [process])"] = sha256(
            repr((fabrication.process, fabrication.force)).encode())
    for number, path in enumerate(paths, start=1):
        # Keyed by position, not path: a moved file with the same content may resume.
        digests[f"target image {number}"] = sha256(Path(path).read_bytes())
    return digests


def resume_state(checkpoint: Path, inputs: dict[str, str], paths: Sequence[Path]
                  ) -> dict[str, Any]:
    """The optimizer state of a checkpoint made with exactly these inputs, else ValueError
    naming the input that changed."""
    if not checkpoint.exists():
        raise ValueError(f"--resume: no checkpoint at {checkpoint}; run without --resume.")
    saved = load_checkpoint(checkpoint)
    before = saved["inputs"]
    changed = [name for name in {**before, **inputs} if before.get(name) != inputs.get(name)]
    targets = {f"target image {n}": f" ({path})" for n, path in enumerate(paths, start=1)}
    changed = [name + targets.get(name, "") for name in changed]
    if changed:
        raise ValueError(f"--resume: {', '.join(changed)} changed since {checkpoint} was saved "
                         "(content compared by SHA-256); resuming would mix two designs. Give "
                         "the inputs of the interrupted run, or run without --resume to start "
                         "again.")
    return dict(saved["state"])


def load_checkpoint(checkpoint: Path) -> dict[str, Any]:
    """A checkpoint's contents, read as data only: torch's weights_only loader builds tensors
    and plain containers and refuses any other object, so a checkpoint from someone else never
    runs code here. ValueError for anything that is not a checkpoint of this format."""
    fix = "Delete it and run without --resume to start again."
    try:
        with warnings.catch_warnings():  # torch warns about the pickle protocol it refuses
            warnings.simplefilter("ignore")
            saved = torch.load(checkpoint, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as err:  # torch's words suggest loading it unsafely: not ours
        raise ValueError(f"--resume: {checkpoint} holds objects other than data (it was written "
                         "by an older aperture-fab, or not by aperture-fab); it was not loaded, "
                         f"since loading it could run code. {fix}") from err
    except (RuntimeError, EOFError, ValueError, OSError) as err:  # truncated or not ours
        raise ValueError(f"--resume: {checkpoint} cannot be read ({err}); it is truncated or "
                         f"not a checkpoint. {fix}") from err
    if not isinstance(saved, dict) or saved.get("format") != CHECKPOINT_FORMAT:
        raise ValueError(f"--resume: {checkpoint} is not an aperture-fab checkpoint of this "
                         f"version (format {CHECKPOINT_FORMAT!r} version {CHECKPOINT_VERSION}); "
                         f"an older aperture-fab made it, or another program. {fix}")
    if saved.get("version") != CHECKPOINT_VERSION:
        raise ValueError(f"--resume: {checkpoint} has checkpoint version "
                         f"{saved.get('version')!r}; this aperture-fab reads version "
                         f"{CHECKPOINT_VERSION}. {fix}")
    state, inputs = saved.get("state"), saved.get("inputs")
    missing = [key for key, kind in CHECKPOINT_STATE.items()
               if not isinstance(state, dict) or not isinstance(state.get(key), kind)]
    if missing or not isinstance(inputs, dict):
        what = ", ".join(f"state[{k!r}]" for k in missing) or "inputs"
        raise ValueError(f"--resume: {checkpoint} lacks {what} or holds another type there; "
                         f"it is damaged or not written by aperture-fab. {fix}")
    return saved
