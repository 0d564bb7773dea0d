"""Bytes in and out: images (decode, resample, PNG), the part's file formats and atomic writes.

Stages return plain values; only the pipeline and the CLI write what these produce to disk.
"""
