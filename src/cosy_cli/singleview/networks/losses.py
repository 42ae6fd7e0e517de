"""The disentangled symmetric loss of CosyPose (paper Appendix A, "Symmetric disentangled loss").

    L = D_l(F(T^k, [v_x, v_y, v^_z], R^), T^)      image-plane translation term ("xy")
      + D_l(F(T^k, [v^_x, v^_y, v_z], R^), T^)      depth term ("z")
      + D_l(F(T^k, [v^_x, v^_y, v^_z], R), T^)      rotation term ("rot")

where ^ marks the targets (:func:`~cosy_cli.singleview.networks.pose_update.update_targets` of the input
pose and the ground truth T^) and D_l is the symmetric distance of the main paper with the L1 norm:

    D_l(T1, T2) = min_{S in S(l)} mean_x || T1 S x - T2 x ||_1        (mm)

Batched over (batch B, symmetries S, points P). Objects with fewer symmetries than S are padded
with identities (:func:`pad_symmetries`), which leaves the minimum unchanged.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

from .pose_update import apply_update_parts, split_output, update_targets


def pad_symmetries(sets: Sequence[np.ndarray | torch.Tensor], dtype=torch.float32) -> torch.Tensor:
    """Stack per-sample symmetry sets [(S_i, 4, 4)] into (B, max S_i, 4, 4), padding with identities."""
    n = max(len(s) for s in sets)
    out = torch.eye(4, dtype=dtype).repeat(len(sets), n, 1, 1)
    for i, s in enumerate(sets):
        out[i, :len(s)] = torch.as_tensor(np.asarray(s), dtype=dtype)
    return out


def symmetric_l1_distance(T_pred: torch.Tensor, T_gt: torch.Tensor, points: torch.Tensor,
                          symmetries: torch.Tensor) -> torch.Tensor:
    """D_l with the L1 norm: (B,) mm.

    T_pred, T_gt (B, 4, 4) mm; points (P, 3) or (B, P, 3) model points (mm); symmetries (S, 4, 4)
    or (B, S, 4, 4), identity-padded. min over S of the mean over points of
    |T_pred S x - T_gt x|_1 (sum of the absolute x, y, z differences).
    """
    B = T_pred.shape[0]
    pts = points.expand(B, -1, -1) if points.dim() == 2 else points
    sym = symmetries.expand(B, -1, -1, -1) if symmetries.dim() == 3 else symmetries
    p_gt = pts @ T_gt[:, :3, :3].transpose(-1, -2) + T_gt[:, None, :3, 3]  # (B, P, 3)
    # The min over S is found without autograd (no (B, S, P, 3) intermediates kept); the distance
    # is then recomputed for the best symmetry only: same value, same (sub)gradient, ~5x cheaper.
    with torch.no_grad():
        TS = T_pred[:, None] @ sym  # (B, S, 4, 4): T_pred S
        p_all = torch.einsum("bsij,bpj->bspi", TS[..., :3, :3], pts) + TS[..., None, :3, 3]
        best = (p_all - p_gt[:, None]).abs().sum(-1).mean(-1).argmin(dim=-1)  # (B,)
        del p_all
    TS = T_pred @ sym[torch.arange(B, device=sym.device), best]  # (B, 4, 4)
    p_pred = pts @ TS[:, :3, :3].transpose(-1, -2) + TS[:, None, :3, 3]
    return (p_pred - p_gt).abs().sum(-1).mean(-1)


def disentangled_loss(out: torch.Tensor, T_in: torch.Tensor, T_gt: torch.Tensor, K_crop: torch.Tensor,
                      points: torch.Tensor, symmetries: torch.Tensor) -> dict[str, torch.Tensor]:
    """The three terms and their sum, each (B,) mm (average with ``.mean()`` for training).

    out (B, 9) network outputs (:mod:`~cosy_cli.singleview.networks.pose_update` layout); T_in (B, 4, 4)
    the input poses (mm); T_gt (B, 4, 4) ground truth (mm); K_crop (B, 3, 3) crop intrinsics (px);
    points (P, 3) / (B, P, 3) mm; symmetries (S, 4, 4) / (B, S, 4, 4). Returns
    {"xy", "z", "rot", "total"}. Gradients flow only through ``out``.
    """
    with torch.no_grad():
        tgt = update_targets(T_in, T_gt, K_crop)
        R_t, vxy_t, vz_t = split_output(tgt)
    R, vxy, vz = split_output(out)
    T_xy = apply_update_parts(T_in, K_crop, R_t, vxy, vz_t)
    T_z = apply_update_parts(T_in, K_crop, R_t, vxy_t, vz)
    T_r = apply_update_parts(T_in, K_crop, R, vxy_t, vz_t)
    T_all = torch.cat([T_xy, T_z, T_r])
    B = out.shape[0]
    rep = (lambda x: x.repeat(3, *([1] * (x.dim() - 1))))
    pts = points if points.dim() == 2 else rep(points)
    sym = symmetries if symmetries.dim() == 3 else rep(symmetries)
    d = symmetric_l1_distance(T_all, rep(T_gt), pts, sym)
    terms = {"xy": d[:B], "z": d[B:2 * B], "rot": d[2 * B:]}
    terms["total"] = terms["xy"] + terms["z"] + terms["rot"]
    return terms
