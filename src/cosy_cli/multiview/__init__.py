"""Multi-view stages: object candidate matching (RANSAC over view pairs + scene graph).

``matching`` holds the pure, batched algorithm (numpy only); ``match_stage`` reads and writes
the files of ``cosy match``.
"""

from .matching import GroupResult, LabelTable, MatchParams, match_group, match_groups, symmetric_distance_rel

__all__ = ["GroupResult", "LabelTable", "MatchParams", "match_group", "match_groups", "symmetric_distance_rel"]
