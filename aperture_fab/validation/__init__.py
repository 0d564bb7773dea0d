"""Judging a part: what the eye sees through it as built beside the design and simple baselines,
over the eye distribution and under tolerances, and the report (JSON, HTML, figures) that says so.
"""
