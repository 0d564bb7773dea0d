"""Measuring a made plate from a back-lit scan (issue 17): find and fit its holes, register them
to the design, name the defects, and write what was made as a design folder reads it.

Stages, each a function from one value to the next (only `job` touches files):
simulate (a design's holes as made -> a scan with its truth, for tests and examples),
scan (image bytes -> a grey transmission image), detect (image -> bright blobs), fit (blobs ->
sub-pixel circles), register (circles -> the scan-to-design transform), measure (all of it ->
a `Measurement`), report (a measurement -> holes.csv, measured.json, the HTML page).
"""
