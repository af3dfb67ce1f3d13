"""Why a DeMoN view, pair or scene group cannot be used: `DamagedDataError` and its
`REASONS`, raised by the reader and the image decoding, caught by the pair generation,
which skips the pair, counts it by reason and goes on.
"""

from __future__ import annotations

# Why a pair (or a whole scene group) could not be used.
REASONS = (
    "corrupt_image",  # missing image dataset, wrong format, undecodable WebP
    "corrupt_depth",  # missing depth dataset, wrong format or metric, undecodable LZ4
    "wrong_extents",  # extents missing or not matching the decompressed depth
    "invalid_depth",  # a depth map without a single finite, positive value
    "missing_camera",  # no camera dataset
    "bad_camera",  # camera values not finite, not 17, no proper rotation, focal <= 0
    "zero_translation",  # ||t|| < 1e-6: skipped as DeMoN skips it (no scale to normalise by)
    "small_baseline",  # baseline <= min_relative_baseline x median depth (a build option)
    "too_few_views",  # a scene group with fewer than two viewpoints
    "bad_viewpoint_pairs",  # viewpoint_pairs malformed or naming a missing view
    "unreadable_group",  # HDF5 error while reading the group
)

# Reasons that skip a pair by the protocol (DeMoN's ||t|| floor) or a build option
# (`min_relative_baseline`) rather than report damage: they are counted apart, neither
# count towards `max_bad_fraction` nor stop a strict build.
FILTER_REASONS = ("zero_translation", "small_baseline")


class DamagedDataError(ValueError):
    """A view, pair or scene group that cannot be used; `reason` is one of `REASONS`."""

    def __init__(self, reason: str, where: str, detail: str):
        if reason not in REASONS:
            raise ValueError(f"unknown damage reason {reason!r}; valid: {REASONS}")
        super().__init__(f"{where}: {reason}: {detail}")
        self.reason = reason
        self.where = where
        self.detail = detail
