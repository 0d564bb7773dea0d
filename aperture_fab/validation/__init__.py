"""Judging a part: what the eye sees through it as built beside the design and simple baselines,
over the eye distribution and under tolerances, as made beside the best regular array, and the
`Report` (verdicts and report.json's content) that says so (`judge.judge`;
`aperture_fab.report` draws it).
"""
