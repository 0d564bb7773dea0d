"""Judging a part: what the eye sees through it as built beside the design and simple baselines,
over the eye distribution and under tolerances, as made beside the best regular array, and the
verdicts and report.json content that say so (`aperture_fab.report` draws them).
"""
