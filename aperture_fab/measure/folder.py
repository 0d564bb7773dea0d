"""A measured plate as a design folder reads it (issue 17, item 2): the design's config with
the process's bias and random errors set to 0 (holes.csv holds the holes as made: nothing is
added to them and no more random error is drawn), and the same for a [process] measured on the
calibration coupon (item 4). Text in, text out: `job` writes the files."""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import tomlkit
from tomlkit.exceptions import TOMLKitError

__all__ = ["AS_MADE_PROCESS", "derived_config"]

#: The [process] values of a measured plate's config: the holes are what was made.
AS_MADE_PROCESS: dict[str, float] = {"radius_bias_mm": 0.0, "radius_sigma_mm": 0.0,
                                     "position_sigma_mm": 0.0}


def derived_config(text: str, source: str, process: Mapping[str, float | str],
                   note: Sequence[str]) -> str:
    """The config `text` (a design.toml, read from `source`) with its [process] table's values
    replaced by `process` (other keys of the design's [process] kept), and `note` as comment
    lines at the top (where it came from, why). ValueError naming `source` when it is not TOML.
    """
    try:
        document = tomlkit.parse(text)
    except TOMLKitError as err:
        raise ValueError(f"{source} is not a TOML config ({err}); give the design folder "
                         "`aperture-fab design` wrote.") from err
    table = document.get("process")
    if table is None:
        table = tomlkit.table()
        document["process"] = table
    for key, value in process.items():
        table[key] = value
    header = "".join(f"# {line}\n" for line in note)
    return header + tomlkit.dumps(document)
