"""Placing the cameras of a group from its linked view pairs, saying how each one was placed.

Pure numpy. Poses are 4x4 ``T_a_b`` matrices in mm. Used by ``cosy refine``
(:mod:`cosy_cli.multiview.refine_stage`).

The rule (the paper's appendix: chain the pairwise relative poses of RANSAC): the largest set
of views connected by links is placed; its gauge view -- the one with most total inliers (ties:
earliest) -- is the world frame; the others are reached over a maximum spanning tree grown from
the gauge (Prim: the link with most inliers first, ties to the earliest views). A link from
RANSAC has >= 3 inliers; the links through one or two objects that ``cosy match`` accepts where
RANSAC leaves views apart have 1-2, so they are used only to reach views no RANSAC link reaches.

Each placed camera records ``placed_by``: ``"gauge (world frame)"``, ``"ransac (N inliers)"``,
``"two objects (obj_id A, B)"``, ``"one object (obj_id A)"``, or ``"known"`` (cameras from the
dataset); views not reached are ``"unplaced"``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Hashable, Sequence

import numpy as np

from .bundle_adjustment import spanning_tree_poses


@dataclass
class Link:
    """A linked view pair: ``T_a_b`` = T_cam_a_cam_b (4, 4, mm), its inlier count, how it was
    linked ("ransac", "two objects", "one object") and the obj_ids of its associations."""

    a: Hashable
    b: Hashable
    T_a_b: np.ndarray
    n_inliers: int
    kind: str = "ransac"
    obj_ids: Sequence[int] = field(default_factory=list)


def describe(link: Link) -> str:
    """How a camera placed through ``link`` was placed (the ``placed_by`` text)."""
    ids = ", ".join(str(int(o)) for o in link.obj_ids)
    if link.kind == "two objects":
        return f"two objects (obj_id {ids})"
    if link.kind == "one object":
        return f"one object (obj_id {ids})"
    return f"ransac ({int(link.n_inliers)} inliers)"


def place_cameras(im_ids: Sequence[Hashable], links: Sequence[Link]):
    """Cameras of a group from its links.

    Returns (placed {im_id: T_world_cam (4, 4)} in tree order, gauge first; placed_by {im_id:
    text} for every view (``"unplaced"`` for the views not reached); placed_from {im_id: the
    placed view it was reached from, or None}; gauge im_id).
    """
    edges = [(ln.a, ln.b, float(ln.n_inliers), ln.T_a_b, ln) for ln in links]
    placed, via, gauge = spanning_tree_poses(im_ids, edges)
    placed_by = {v: "unplaced" for v in im_ids}
    placed_from: dict = {v: None for v in im_ids}
    placed_by[gauge] = "gauge (world frame)"
    for b, (a, ln) in via.items():
        placed_by[b] = describe(ln)
        placed_from[b] = a
    return placed, placed_by, placed_from, gauge
