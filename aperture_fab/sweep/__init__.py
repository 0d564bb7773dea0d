"""Design-space sweeps: many design jobs over config keys, on one machine or a Ray cluster.

`aperture-fab sweep sweep.toml --out outputs/sweep/` (see `command`); the parts: `spec` reads
and checks the sweep file, `run` runs the points (Ray or serial, resumable), `results` writes
the table, the Pareto front and the page. Ray, Optuna and pyarrow load only when used.
"""

from __future__ import annotations

from aperture_fab.sweep.spec import SweepSpec, load_spec

__all__ = ["SweepSpec", "load_spec"]
