"""The jobs the commands run: each chains the stages on plain values and is the one place, with the
CLI, that reads and writes files.
"""

from aperture_fab.pipeline.design_job import DesignResult, design, run_design

__all__ = ["DesignResult", "design", "run_design"]
