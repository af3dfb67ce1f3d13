"""Analyses of trained models and of the data: pose probes, depth error against
flow error, filter banks, where learning wins against the classical pipeline, the
self-supervised diagnosis; depth methods trained and scored alike on one dataset
(`comparison`).
"""
