"""Scoring depth: the metrics, the one evaluation loop with its references
(`evaluate`), depth maps other systems stored, and the reports.
"""
