"""VGGT camera encodings <-> extrinsics / intrinsics, and unprojection of depth maps.

Encoding ``absT_quaR_FoV`` (9 numbers per frame): translation t (3), quaternion **x, y, z, w** (4, not
necessarily unit length), vertical FoV ``fov_h`` and horizontal FoV ``fov_w`` in radians. The extrinsic
is camera-from-world ``T_cam_world`` = [R | t] in the OpenCV camera convention. Intrinsics use the
*network input* size: ``fx = (W/2)/tan(fov_w/2)``, ``fy = (H/2)/tan(fov_h/2)``, ``cx = W/2``, ``cy = H/2``.
"""

from __future__ import annotations

import numpy as np
import torch

from vggt_slam_pp.errors import ModelError


def quaternion_xyzw_to_matrix(q: torch.Tensor) -> torch.Tensor:
    """[..., 4] (x, y, z, w), any non-zero norm -> rotation [..., 3, 3] (uses s = 2/|q|²)."""
    x, y, z, w = q.unbind(-1)
    s = 2.0 / (q * q).sum(-1)
    R = torch.stack([
        1 - s * (y * y + z * z), s * (x * y - z * w), s * (x * z + y * w),
        s * (x * y + z * w), 1 - s * (x * x + z * z), s * (y * z - x * w),
        s * (x * z - y * w), s * (y * z + x * w), 1 - s * (x * x + y * y)], dim=-1)
    return R.reshape(*q.shape[:-1], 3, 3)


def matrix_to_quaternion_xyzw(R: torch.Tensor) -> torch.Tensor:
    """Rotation [..., 3, 3] -> unit quaternion [..., 4] (x, y, z, w) with w >= 0.

    Chooses the best-conditioned of the four candidate formulas (largest of 1±trace terms).
    """
    m = R.reshape(*R.shape[:-2], 9)
    m00, m01, m02, m10, m11, m12, m20, m21, m22 = m.unbind(-1)
    terms = torch.stack([1 + m00 + m11 + m22, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22,
                         1 - m00 - m11 + m22], dim=-1)
    abs4 = torch.sqrt(torch.clamp(terms, min=0))  # 2|w|, 2|x|, 2|y|, 2|z|
    cands = torch.stack([
        torch.stack([abs4[..., 0] ** 2, m21 - m12, m02 - m20, m10 - m01], dim=-1),
        torch.stack([m21 - m12, abs4[..., 1] ** 2, m10 + m01, m02 + m20], dim=-1),
        torch.stack([m02 - m20, m10 + m01, abs4[..., 2] ** 2, m12 + m21], dim=-1),
        torch.stack([m10 - m01, m20 + m02, m21 + m12, abs4[..., 3] ** 2], dim=-1)], dim=-2)  # (w,x,y,z)
    cands = cands / (2.0 * torch.clamp(abs4[..., None], min=0.1))
    best = abs4.argmax(dim=-1)
    wxyz = torch.gather(cands, -2, best[..., None, None].expand(*best.shape, 1, 4)).squeeze(-2)
    wxyz = torch.where(wxyz[..., :1] < 0, -wxyz, wxyz)
    return torch.cat([wxyz[..., 1:], wxyz[..., :1]], dim=-1)


def pose_encoding_to_extri_intri(pose_enc: torch.Tensor, image_size_hw: tuple[int, int]
                                 ) -> tuple[torch.Tensor, torch.Tensor]:
    """pose_enc [..., 9] -> (extrinsic ``T_cam_world`` [..., 3, 4], intrinsic [..., 3, 3])."""
    if pose_enc.shape[-1] != 9:
        raise ModelError(f"pose encoding must have 9 values per frame, got shape {tuple(pose_enc.shape)}")
    H, W = image_size_hw
    R = quaternion_xyzw_to_matrix(pose_enc[..., 3:7])
    extrinsic = torch.cat([R, pose_enc[..., :3, None]], dim=-1)
    fy = (H / 2.0) / torch.tan(pose_enc[..., 7] / 2.0)
    fx = (W / 2.0) / torch.tan(pose_enc[..., 8] / 2.0)
    K = torch.zeros(*pose_enc.shape[:-1], 3, 3, dtype=pose_enc.dtype, device=pose_enc.device)
    K[..., 0, 0] = fx
    K[..., 1, 1] = fy
    K[..., 0, 2] = W / 2
    K[..., 1, 2] = H / 2
    K[..., 2, 2] = 1.0
    return extrinsic, K


def extri_intri_to_pose_encoding(extrinsic: torch.Tensor, intrinsic: torch.Tensor,
                                 image_size_hw: tuple[int, int]) -> torch.Tensor:
    """Inverse of :func:`pose_encoding_to_extri_intri`: [..., 3, 4] + [..., 3, 3] -> [..., 9] float32."""
    H, W = image_size_hw
    quat = matrix_to_quaternion_xyzw(extrinsic[..., :3, :3])
    fov_h = 2 * torch.atan((H / 2) / intrinsic[..., 1, 1])
    fov_w = 2 * torch.atan((W / 2) / intrinsic[..., 0, 0])
    return torch.cat([extrinsic[..., :3, 3], quat, fov_h[..., None], fov_w[..., None]], dim=-1).float()


def extrinsic_to_T_cam_world(extrinsic: np.ndarray | torch.Tensor) -> np.ndarray:
    """[..., 3, 4] camera-from-world -> homogeneous ``T_cam_world`` [..., 4, 4] float64."""
    E = np.asarray(extrinsic.detach().cpu() if isinstance(extrinsic, torch.Tensor) else extrinsic,
                   dtype=np.float64)
    T = np.zeros((*E.shape[:-2], 4, 4))
    T[..., :3, :] = E
    T[..., 3, 3] = 1.0
    return T


def unproject_depth_map_to_point_map(depth, extrinsic, intrinsic) -> np.ndarray:
    """World points [S, H, W, 3] **float64** from depth [S,H,W] or [S,H,W,1], ``T_cam_world`` [S,3,4]
    and zero-skew intrinsics [S,3,3] (tensors or arrays).

    Pixel grid = integer indices (u = column, v = row, no +0.5), exactly as the reference, so with its
    principal point W/2, H/2 the grid is half a pixel off the image centre. Camera points are formed
    in float32; the world transform promotes to float64.
    """
    def np_(a):
        return a.detach().cpu().numpy() if isinstance(a, torch.Tensor) else np.asarray(a)

    d, E, K = np_(depth), np_(extrinsic), np_(intrinsic)
    if d.ndim == 4 and d.shape[-1] == 1:
        d = d[..., 0]
    if d.ndim != 3 or E.shape != (d.shape[0], 3, 4) or K.shape != (d.shape[0], 3, 3):
        raise ModelError(f"unproject: expected depth [S,H,W], extrinsic [S,3,4], intrinsic [S,3,3]; got "
                         f"{d.shape}, {E.shape}, {K.shape}")
    if np.any(K[:, 0, 1] != 0) or np.any(K[:, 1, 0] != 0):
        raise ModelError("unproject: intrinsics must have zero skew")
    S, H, W = d.shape
    u, v = np.meshgrid(np.arange(W), np.arange(H))
    out = np.empty((S, H, W, 3), dtype=np.float64)
    for s in range(S):
        fx, fy, cx, cy = K[s, 0, 0], K[s, 1, 1], K[s, 0, 2], K[s, 1, 2]
        cam = np.stack([(u - cx) * d[s] / fx, (v - cy) * d[s] / fy, d[s]], axis=-1).astype(np.float32)
        R, t = E[s, :3, :3].astype(np.float64), E[s, :3, 3].astype(np.float64)
        out[s] = cam.astype(np.float64) @ R + (-R.T @ t)  # R^T x - R^T t
    return out
