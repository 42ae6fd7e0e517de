"""The pose update F of CosyPose (paper Appendix A, "Transformation parametrization"), in torch.

The network predicts 9 numbers per crop, in this order::

    [e1 (3), e2 (3), v_x, v_y, v_z]

- ``e1, e2``: the rotation R in the 6D representation (Zhou et al. 2019): the first two columns of
  R before Gram-Schmidt orthonormalisation (:func:`cosy_cli.geometry.torch_ops.rot6d_to_matrix`).
  The paper prints e3' = e1' x e2 / ||e2||, which is orthonormal only when e2 is orthogonal to
  e1; we use the Gram-Schmidt form of the cited paper (identical on exact rotations).
- ``v_x, v_y``: image-plane shift (px, in the crop) of the projected object origin.
- ``v_z``: relative depth, linear as in the paper (z^{k+1} = v_z z^k; DeepIM used exp(-v_z)).

With T^k = [R^k | (x^k, y^k, z^k)] (mm) and the crop focal lengths f_x^C, f_y^C (px)::

    z^{k+1} = v_z z^k
    x^{k+1} = (v_x / f_x^C + x^k / z^k) z^{k+1}
    y^{k+1} = (v_y / f_y^C + y^k / z^k) z^{k+1}
    R^{k+1} = R R^k

R multiplies on the left: it is a rotation expressed in the camera frame, about the object's
origin (the translation is updated separately). The identity update is
``[1, 0, 0, 0, 1, 0, 0, 0, 1]`` (:data:`IDENTITY_OUTPUT`).
"""

from __future__ import annotations

import torch

from ...geometry.torch_ops import matrix_to_rot6d, rot6d_to_matrix

N_OUTPUTS = 9
IDENTITY_OUTPUT = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)


def split_output(out: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(B, 9) network output -> R (B, 3, 3), v_xy (B, 2) px, v_z (B,) (relative, 1 = unchanged)."""
    return rot6d_to_matrix(out[..., :6]), out[..., 6:8], out[..., 8]


def apply_update_parts(T_in: torch.Tensor, K_crop: torch.Tensor, R: torch.Tensor, v_xy: torch.Tensor,
                       v_z: torch.Tensor) -> torch.Tensor:
    """F(T_in, [v_x, v_y, v_z], R) -> T_out (B, 4, 4), mm.

    T_in (B, 4, 4) mm; K_crop (B, 3, 3) the crop intrinsics (only f_x, f_y are used, px);
    R (B, 3, 3); v_xy (B, 2) px; v_z (B,).
    """
    t = T_in[..., :3, 3]
    z_in = t[..., 2]
    z = v_z * z_in
    f = torch.stack([K_crop[..., 0, 0], K_crop[..., 1, 1]], dim=-1)
    xy = (v_xy / f + t[..., :2] / z_in[..., None]) * z[..., None]
    top = torch.cat([R @ T_in[..., :3, :3], torch.cat([xy, z[..., None]], -1)[..., None]], dim=-1)
    bottom = torch.zeros_like(T_in[..., 3:, :])
    bottom[..., 3] = 1.0
    return torch.cat([top, bottom], dim=-2)


def apply_update(T_in: torch.Tensor, out: torch.Tensor, K_crop: torch.Tensor) -> torch.Tensor:
    """T^{k+1} = F(T^k, network output (B, 9)) with the crop intrinsics K_crop (B, 3, 3)."""
    R, v_xy, v_z = split_output(out)
    return apply_update_parts(T_in, K_crop, R, v_xy, v_z)


def update_targets(T_in: torch.Tensor, T_target: torch.Tensor, K_crop: torch.Tensor) -> torch.Tensor:
    """The outputs (B, 9) the network should predict so that F(T_in, output) = T_target.

    R = R_target R_in^T; v_z = z_target / z_in; v_x = f_x^C (x_target / z_target - x_in / z_in)
    (px), v_y likewise. Both poses must be in front of the camera (z > 0).
    """
    t_in = T_in[..., :3, 3]
    t_tg = T_target[..., :3, 3]
    R = T_target[..., :3, :3] @ T_in[..., :3, :3].transpose(-1, -2)
    v_z = t_tg[..., 2] / t_in[..., 2]
    f = torch.stack([K_crop[..., 0, 0], K_crop[..., 1, 1]], dim=-1)
    v_xy = f * (t_tg[..., :2] / t_tg[..., 2:3] - t_in[..., :2] / t_in[..., 2:3])
    return torch.cat([matrix_to_rot6d(R), v_xy, v_z[..., None]], dim=-1)


def identity_output(batch: int, dtype=torch.float32, device=None) -> torch.Tensor:
    """(batch, 9) outputs that leave poses unchanged."""
    return torch.tensor(IDENTITY_OUTPUT, dtype=dtype, device=device).expand(batch, N_OUTPUTS).clone()
