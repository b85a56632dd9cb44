"""An oracle VGGT: a weight-free ``torch.nn.Module`` with VGGT's input/output contract whose outputs are
the synthetic world's ground truth, as a perfect VGGT would predict them for the images it receives.

It proves the ``vggt`` backbone path end to end without weights (issue 22): preprocessing, the pose
encoding and its decoding, network pixels back to original pixels, unprojection, ``T_cam_submap`` from
camera-from-world extrinsics, confidence filtering and the Sim(3) chaining of dense submaps.

**Independence.** Everything here is derived from the public contract
(``../shared/reference/vggt_contract.md`` §1-4) and the synthetic ground truth; it imports none of our
preprocessing or camera-decoding code (``vggt_slam_pp.models``), so an error there shows up as a
difference between what the oracle says and what the path recovers. The preprocessing geometry
(size rule, bicubic resize of the corner-based extent, central crop, white pad, pad-to-largest) is
re-derived from the contract and the original image size.

**What it is told.** Before each forward call, ``oracle.frames`` is set to one :class:`OracleView` per
input frame (ground-truth ``T_world_cam``, depth at original resolution with 0 = unknown, original
intrinsics, optionally the original image). :func:`vggt_slam_pp.frontend.backbones.oracle.oracle_backbone` does it
for a synthetic source: it returns a :class:`~vggt_slam_pp.frontend.backbones.vggt.VggtBackbone`
running this model, wrapped so that the oracle knows the frames of each call.

**Outputs** (B = 1; S frames; H x W the network input; float32):

* ``pose_enc`` [1,S,9] = translation, quaternion (x, y, z, w; w >= 0), fov_h, fov_w of the
  camera-from-world extrinsic, world = frame 0's camera (OpenCV); ``pose_enc_list`` = 4 copies.
  FoVs are those of the true camera after resizing (``fov = 2 atan((size/2) / f_network)``).
* ``depth`` [1,S,H,W,1]: z-depth at each network pixel (centre), sampled from the ground-truth depth
  map at the original-image location that preprocessing put there. Inverse depth is interpolated
  bilinearly (exact on planes) where the four neighbours are valid and on one surface; across a depth
  edge the nearest original pixel is used. Pixels without a surface (sky, depth 0) and padding get a
  far depth (``far_depth``, always > 0 as VGGT's ``exp`` activation) and the lowest confidence.
* ``depth_conf`` [1,S,H,W] = 1 + exp(c): c = 4 on surfaces, 1 at depth edges, -8 on sky and padding;
  with depth noise c is lowered by |relative error| / ``depth_noise`` (confidence tracks the error).
* ``world_points`` [1,S,H,W,3]: the depth unprojected with the *true* network camera into frame 0's
  camera frame; ``world_points_conf`` = ``depth_conf``; ``images`` = the input, echoed (eval mode).
  There is no track head: ``query_points`` is accepted and ignored (no ``track``/``vis``/``conf``).
* ``normalize=True`` (default) scales each call's scene so that the mean distance of its surface
  points to frame 0's camera is 1 (the VGGT paper's training normalisation); ``False`` keeps metres.

**Noise** (:class:`OracleNoise`, seeded by ``default_rng([seed, first frame key])`` so one call's noise
does not depend on the run's history), the same model as the simulated backbone's: multiplicative
depth noise N(0, ``depth_noise``) per network pixel; pose noise on frames >= 1, rotation N(0,
``rot_noise_deg``) per axis and translation N(0, ``trans_noise`` x distance from frame 0) per axis,
applied on the left of the camera-from-world extrinsic; and a per-call scale error exp(N(0,
``scale_error``)) on translations, depths and points. World points use the noisy depth and pose.

**A limit of the contract, not of our code.** The 9-number encoding has no principal point: decoding
puts it at (W/2, H/2) on an integer pixel grid, while a centred camera after the resize sits at
((W-1)/2, (H-1)/2). Even a perfect VGGT is therefore half a network pixel off in the principal point
(0.5 / scale original pixels, 0.15 px for 160-pixel-wide inputs); :func:`consistency` reports it.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from vggt_slam_pp.errors import ModelError

log = logging.getLogger(__name__)

__all__ = ["OracleNoise", "OracleVggt", "OracleView", "Placement", "consistency", "placements", "sample_depth"]

_C_SURFACE, _C_EDGE, _C_NONE = 4.0, 1.0, -8.0


@dataclass(frozen=True)
class OracleNoise:
    """Noise on the oracle's outputs (all zero: exact). Same meaning as ``SimulatedNoise``'s fields."""

    depth_noise: float = 0.0  # relative, per network pixel
    scale_error: float = 0.0  # sigma of the log of the per-call scale
    rot_noise_deg: float = 0.0  # per axis, frames >= 1
    trans_noise: float = 0.0  # x distance from frame 0, per axis, frames >= 1

    @property
    def zero(self) -> bool:
        return not (self.depth_noise or self.scale_error or self.rot_noise_deg or self.trans_noise)


@dataclass(frozen=True, eq=False)
class OracleView:
    """Ground truth of one frame: ``T_world_cam`` [4,4] (OpenCV camera), ``depth`` [H0,W0] z-depth
    (0 = unknown), ``K`` [3,3] original intrinsics (pixel centres at integers), optional original
    ``image`` uint8 [H0,W0,3] (checked against the network input) and a ``key`` for seeding."""

    T_world_cam: np.ndarray
    depth: np.ndarray
    K: np.ndarray
    image: np.ndarray | None = None
    key: int = 0


@dataclass(frozen=True)
class Placement:
    """Where one original image lies in the network input, as the contract's preprocessing puts it:
    a network pixel centre ``x_net`` shows original position ``(x_net + 0.5 - offset_x) / scale_x - 0.5``
    (a resize maps the corner-based extent; OpenCV pixel centres at integers); same for y."""

    original_hw: tuple[int, int]
    resized_hw: tuple[int, int]  # size after the resize, before crop / pad
    network_hw: tuple[int, int]
    scale_x: float
    scale_y: float
    offset_x: float
    offset_y: float

    def original_xy(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Original-image coordinates (x, y) [H,W] of every network pixel, and the mask of pixels that
        show the image (not padding)."""
        H, W = self.network_hw
        u = np.arange(W, dtype=np.float64)
        v = np.arange(H, dtype=np.float64)
        x = (u + 0.5 - self.offset_x) / self.scale_x - 0.5
        y = (v + 0.5 - self.offset_y) / self.scale_y - 0.5
        h0, w0 = self.original_hw
        inside = ((y >= -0.5) & (y <= h0 - 0.5))[:, None] & ((x >= -0.5) & (x <= w0 - 0.5))[None, :]
        return np.broadcast_to(x[None, :], (H, W)), np.broadcast_to(y[:, None], (H, W)), inside

    def network_K(self, K: np.ndarray) -> np.ndarray:
        """The true camera of the network input, from the original ``K`` [3,3]."""
        K = np.asarray(K, dtype=np.float64)
        return np.array([[K[0, 0] * self.scale_x, 0.0, (K[0, 2] + 0.5) * self.scale_x - 0.5 + self.offset_x],
                         [0.0, K[1, 1] * self.scale_y, (K[1, 2] + 0.5) * self.scale_y - 0.5 + self.offset_y],
                         [0.0, 0.0, 1.0]])


def placements(sizes_hw: Sequence[tuple[int, int]], mode: str = "crop", target: int = 518) -> list[Placement]:
    """The contract's preprocessing geometry (§1) for images of original sizes ``(H0, W0)`` in one call."""
    if mode not in ("crop", "pad"):
        raise ModelError(f"oracle: unknown preprocessing mode {mode!r}")
    out = []
    for h0, w0 in sizes_hw:
        if mode == "pad" and w0 < h0:
            nh, nw = target, round(w0 * target / h0 / 14) * 14
        else:
            nw, nh = target, round(h0 * target / w0 / 14) * 14
        ox = oy = 0.0
        H, W = nh, nw
        if mode == "crop" and nh > target:
            oy, H = -float((nh - target) // 2), target
        elif mode == "pad":
            ox, oy, H, W = float((target - nw) // 2), float((target - nh) // 2), target, target
        out.append(Placement((h0, w0), (nh, nw), (H, W), nw / w0, nh / h0, ox, oy))
    H, W = max(p.network_hw[0] for p in out), max(p.network_hw[1] for p in out)
    return [Placement(p.original_hw, p.resized_hw, (H, W), p.scale_x, p.scale_y,
                      p.offset_x + (W - p.network_hw[1]) // 2, p.offset_y + (H - p.network_hw[0]) // 2)
            for p in out]


def sample_depth(depth: np.ndarray, x: np.ndarray, y: np.ndarray, edge_ratio: float = 1.1
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Depth of a map [H0,W0] (0 = unknown) at original positions ``x``, ``y`` (any shape).

    Returns (depth, kind) with kind 2 = smooth (bilinear inverse depth, all four neighbours valid and
    within ``edge_ratio`` of each other: exact on a plane), 1 = edge (nearest valid pixel), 0 = none
    (depth 0)."""
    d = np.asarray(depth, dtype=np.float64)
    h0, w0 = d.shape
    xc = np.clip(x, 0.0, w0 - 1.0)
    yc = np.clip(y, 0.0, h0 - 1.0)
    x0 = np.minimum(np.floor(xc).astype(np.int64), w0 - 2 if w0 > 1 else 0)
    y0 = np.minimum(np.floor(yc).astype(np.int64), h0 - 2 if h0 > 1 else 0)
    x1, y1 = np.minimum(x0 + 1, w0 - 1), np.minimum(y0 + 1, h0 - 1)
    ax, ay = xc - x0, yc - y0
    n = [d[y0, x0], d[y0, x1], d[y1, x0], d[y1, x1]]
    ok = (n[0] > 0) & (n[1] > 0) & (n[2] > 0) & (n[3] > 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = [np.where(ok, 1.0 / np.where(ok, q, 1.0), 0.0) for q in n]
        lo = np.minimum(np.minimum(inv[0], inv[1]), np.minimum(inv[2], inv[3]))
        hi = np.maximum(np.maximum(inv[0], inv[1]), np.maximum(inv[2], inv[3]))
        smooth = ok & (hi <= edge_ratio * lo)
        bil = (inv[0] * (1 - ax) * (1 - ay) + inv[1] * ax * (1 - ay) + inv[2] * (1 - ax) * ay + inv[3] * ax * ay)
        out = np.where(smooth, 1.0 / np.where(smooth, bil, 1.0), 0.0)
    near = d[np.clip(np.rint(yc).astype(np.int64), 0, h0 - 1), np.clip(np.rint(xc).astype(np.int64), 0, w0 - 1)]
    edge = ~smooth & (near > 0)
    out = np.where(edge, near, out)
    kind = np.where(smooth, 2, np.where(edge, 1, 0)).astype(np.int8)
    return out, kind


def _quat_xyzw(R: np.ndarray) -> np.ndarray:
    q = Rotation.from_matrix(R).as_quat()  # scipy: scalar last (x, y, z, w), unit
    return -q if q[3] < 0 else q


def _resample_image(image: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    import cv2

    return cv2.remap(image, x.astype(np.float32), y.astype(np.float32), cv2.INTER_LINEAR,
                     borderMode=cv2.BORDER_REPLICATE).astype(np.float32) / 255.0


class OracleVggt(torch.nn.Module):
    """VGGT's forward contract, answered from ground truth (see the module docstring).

    Args:
        mode, target_size: the preprocessing the caller applied (the contract's ``mode``; 518).
        noise: :class:`OracleNoise` (None: exact); ``seed`` for its random numbers.
        normalize: scale each call's scene to a mean point distance of 1 (VGGT's training convention).
        far_depth: depth (metres, before normalisation) reported where there is no surface.
        image_tolerance: the largest mean absolute difference (intensity in [0,1]) between the received
            image and the original resampled with the derived geometry; above it the call fails with a
            :class:`~vggt_slam_pp.errors.ModelError` (the images were not preprocessed as the contract
            says). None: no check. Measured on the synthetic worlds: 0.0014-0.0033 when right (bicubic
            resize vs the bilinear resampling here), 0.004-0.007 one network pixel off, 0.05-0.08 with
            the colour channels swapped, 0.18-0.33 upside down.
    """

    def __init__(self, mode: str = "crop", target_size: int = 518, noise: OracleNoise | None = None,
                 seed: int = 0, normalize: bool = True, far_depth: float = 1000.0,
                 image_tolerance: float | None = 0.02) -> None:
        super().__init__()
        if mode not in ("crop", "pad"):
            raise ModelError(f"oracle: unknown preprocessing mode {mode!r}")
        self.mode, self.target_size = mode, int(target_size)
        self.noise = noise or OracleNoise()
        self.seed, self.normalize, self.far_depth = seed, normalize, float(far_depth)
        self.image_tolerance = image_tolerance
        self.frames: list[OracleView] | None = None
        self.calls: list[dict] = []  # per call: placements, scale, image errors (for tests and logs)

    def forward(self, images: torch.Tensor, query_points: torch.Tensor | None = None) -> dict:
        if images.ndim == 4:
            images = images[None]
        if images.ndim != 5 or images.shape[2] != 3:
            raise ModelError(f"oracle: images must be [S,3,H,W] or [B,S,3,H,W], got {tuple(images.shape)}")
        B, S, _, H, W = images.shape
        views, self.frames = self.frames, None
        if B != 1:
            raise ModelError("oracle: one scene per call (B = 1)")
        if views is None or len(views) != S:
            raise ModelError(f"oracle: told {0 if views is None else len(views)} frames, got {S} images "
                             "(set `oracle.frames` before each call)")
        if H % 14 or W % 14:
            raise ModelError(f"oracle: input {H}x{W} is not a multiple of 14")
        places = placements([v.depth.shape for v in views], self.mode, self.target_size)
        if places[0].network_hw != (H, W):
            raise ModelError(f"oracle: input is {H}x{W} but the contract's {self.mode} preprocessing of "
                             f"{places[0].original_hw[0]}x{places[0].original_hw[1]} gives "
                             f"{places[0].network_hw[0]}x{places[0].network_hw[1]}")
        n = self.noise
        rng = np.random.default_rng([self.seed, int(views[0].key)])
        received = images[0].detach().float().cpu().numpy()
        T_c0_world = np.linalg.inv(views[0].T_world_cam)
        E = np.stack([np.linalg.inv(v.T_world_cam) @ views[0].T_world_cam for v in views])  # T_ci_c0
        E[0] = np.eye(4)
        scale = self._scale(views, T_c0_world)
        if n.scale_error:
            scale *= float(np.exp(rng.normal(0.0, n.scale_error)))
        depth = np.zeros((S, H, W))
        conf_c = np.zeros((S, H, W))
        pts = np.zeros((S, H, W, 3), np.float32)
        enc = np.zeros((S, 9))
        image_err = []
        for i, (v, p) in enumerate(zip(views, places, strict=True)):
            if i > 0 and (n.rot_noise_deg or n.trans_noise):
                dist = float(np.linalg.norm(np.linalg.inv(E[i])[:3, 3]))
                noise = np.eye(4)
                noise[:3, :3] = Rotation.from_rotvec(rng.normal(0, np.radians(n.rot_noise_deg), 3)).as_matrix()
                noise[:3, 3] = rng.normal(0, n.trans_noise * dist, 3)
                E[i] = noise @ E[i]
            x, y, inside = p.original_xy()
            d, kind = sample_depth(v.depth, x, y)
            kind = np.where(inside, kind, 0)
            c = np.where(kind == 2, _C_SURFACE, np.where(kind == 1, _C_EDGE, _C_NONE))
            d = np.where(kind > 0, d, self.far_depth)
            if n.depth_noise:
                rel = rng.normal(0.0, n.depth_noise, d.shape)
                d = d * (1.0 + rel)
                c = c - np.abs(rel) / n.depth_noise
            depth[i] = d * scale
            conf_c[i] = c
            Kn = p.network_K(v.K)
            uu, vv = np.meshgrid(np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64))
            cam = np.stack([(uu - Kn[0, 2]) / Kn[0, 0] * depth[i], (vv - Kn[1, 2]) / Kn[1, 1] * depth[i],
                            depth[i]], axis=-1)
            R, t = E[i][:3, :3], E[i][:3, 3] * scale
            pts[i] = (cam - t) @ R  # X_c0 = R^T (X_ci - t)
            enc[i, :3] = t
            enc[i, 3:7] = _quat_xyzw(R)
            enc[i, 7] = 2.0 * np.arctan((H / 2.0) / Kn[1, 1])
            enc[i, 8] = 2.0 * np.arctan((W / 2.0) / Kn[0, 0])
            image_err.append(self._check_image(v, x, y, inside, received[i]))
        self.calls.append({"keys": [int(v.key) for v in views], "placements": places, "scale": scale,
                           "image_error": image_err})
        log.debug("oracle: %d frames from %d, %s, scale %.4g, image error <= %.4f", S, views[0].key, self.mode,
                  scale, max(image_err))
        tol = self.image_tolerance
        bad = [(i, e) for i, e in enumerate(image_err) if tol is not None and e > tol]
        if bad:
            raise ModelError(f"oracle: the network input of frame(s) {[i for i, _ in bad]} does not show the "
                             f"original image where the contract's {self.mode} preprocessing puts it "
                             f"(mean abs difference {max(e for _, e in bad):.3f} > {tol})")
        dev = images.device
        f32 = dict(dtype=torch.float32, device=dev)
        conf = torch.as_tensor(1.0 + np.exp(conf_c), **f32)[None]
        pose_enc = torch.as_tensor(enc, **f32)[None]
        out = {"pose_enc": pose_enc, "pose_enc_list": [pose_enc.clone() for _ in range(4)],
               "depth": torch.as_tensor(depth, **f32)[None, ..., None], "depth_conf": conf,
               "world_points": torch.as_tensor(pts, **f32)[None], "world_points_conf": conf.clone()}
        if not self.training:
            out["images"] = images
        return out

    def _scale(self, views: Sequence[OracleView], T_c0_world: np.ndarray) -> float:
        if not self.normalize:
            return 1.0
        dists = []
        for v in views:
            h0, w0 = v.depth.shape
            yy, xx = np.mgrid[0:h0:2, 0:w0:2]
            d = v.depth[yy, xx].astype(np.float64)
            ok = d > 0
            K = np.asarray(v.K, dtype=np.float64)
            cam = np.stack([(xx[ok] - K[0, 2]) / K[0, 0] * d[ok], (yy[ok] - K[1, 2]) / K[1, 1] * d[ok], d[ok]], 1)
            T = T_c0_world @ v.T_world_cam
            dists.append(np.linalg.norm(cam @ T[:3, :3].T + T[:3, 3], axis=1))
        dists = np.concatenate(dists) if dists else np.zeros(0)
        return 1.0 / float(dists.mean()) if len(dists) and dists.mean() > 0 else 1.0

    def _check_image(self, v: OracleView, x, y, inside, received: np.ndarray) -> float:
        if v.image is None or self.image_tolerance is None:
            return 0.0
        got = np.moveaxis(received, 0, -1)
        expected = _resample_image(v.image, x, y)
        err = np.abs(got - expected).mean(axis=-1)
        pad_err = np.abs(got - 1.0).mean(axis=-1)  # padding is white (1.0)
        return float(np.where(inside, err, pad_err).mean())


# ------------------------------------------------------------------------------------------ checks
@dataclass
class Consistency:
    """How far a prediction is from the ground truth (see :func:`consistency`)."""

    rotation_deg: float = 0.0  # largest rotation error of T_cam_submap
    translation_rel: float = 0.0  # largest |t - s t_gt| / (s * scene size)
    focal_rel: float = 0.0  # largest relative error of fx, fy in original pixels
    principal_px: float = 0.0  # largest principal point error in original pixels
    reprojection_px: float = 0.0  # largest reprojection error of the points (original pixels)
    depth_rel: float = 0.0  # median |z / s - z_gt| / z_gt over smooth ground-truth pixels
    scale: float = 1.0  # the prediction's scale (median z / z_gt)
    points: int = 0
    per_frame: list = field(default_factory=list)


def consistency(pred, views: Sequence[OracleView], max_points: int = 5000) -> Consistency:
    """Check a ``SubmapPrediction`` against the ground truth of its frames, using only the prediction's
    documented meaning: ``T_cam_submap`` (camera-from-submap, submap = frame 0's camera, up to scale),
    ``intrinsics`` at network resolution and ``to_original`` (network -> original pixels), points in
    the submap frame observed at ``pixels`` (original pixels). Points are brought into their camera with
    ``T_cam_submap`` and projected with the true original camera; their depth is compared with the
    ground-truth depth at their pixel."""
    r = Consistency()
    T0 = views[0].T_world_cam
    ratios, rels, reproj = [], [], []
    cams = []
    for i, v in enumerate(views):
        if not pred.valid[i] or len(pred.points[i]) == 0:
            cams.append(None)
            continue
        T = np.asarray(pred.T_cam_submap[i], dtype=np.float64)
        X = pred.points[i].astype(np.float64) @ T[:3, :3].T + T[:3, 3]
        pix = pred.pixels[i].astype(np.float64)
        if len(X) > max_points:
            pick = np.random.default_rng(i).choice(len(X), max_points, replace=False)
            X, pix = X[pick], pix[pick]
        K = np.asarray(v.K, dtype=np.float64)
        d, kind = sample_depth(v.depth, pix[:, 0], pix[:, 1])
        h0, w0 = v.depth.shape
        ok = (kind == 2) & (X[:, 2] > 0) & (pix[:, 0] >= 0) & (pix[:, 0] <= w0 - 1) & (pix[:, 1] >= 0) & \
            (pix[:, 1] <= h0 - 1)
        cams.append((X[ok], pix[ok], d[ok], K))
        if ok.any():
            ratios.append(X[ok, 2] / d[ok])
    r.scale = float(np.median(np.concatenate(ratios))) if ratios else float("nan")
    for i, v in enumerate(views):
        entry = {"frame": int(v.key)}
        T_gt = np.linalg.inv(v.T_world_cam) @ T0
        T = np.asarray(pred.T_cam_submap[i], dtype=np.float64)
        dR = T[:3, :3] @ T_gt[:3, :3].T
        # angle from the chord (accurate near 0, unlike arccos of the trace): |dR - I|_F = 2 sqrt(2) sin(a/2)
        chord = min(1.0, float(np.linalg.norm(dR - np.eye(3))) / np.sqrt(8))
        entry["rotation_deg"] = float(np.degrees(2 * np.arcsin(chord)))
        entry["translation"] = float(np.linalg.norm(T[:3, 3] / r.scale - T_gt[:3, 3]))
        Ko = np.asarray(pred.to_original[i], dtype=np.float64) @ np.asarray(pred.intrinsics[i], dtype=np.float64)
        K = np.asarray(v.K, dtype=np.float64)
        entry["focal_rel"] = float(max(abs(Ko[0, 0] / K[0, 0] - 1), abs(Ko[1, 1] / K[1, 1] - 1)))
        entry["principal_px"] = float(np.hypot(Ko[0, 2] - K[0, 2], Ko[1, 2] - K[1, 2]))
        c = cams[i]
        if c is not None and len(c[0]):
            X, pix, d, _ = c
            proj = X @ K.T
            proj = proj[:, :2] / proj[:, 2:3]
            e = np.linalg.norm(proj - pix, axis=1)
            entry["reprojection_px"] = float(e.max())
            entry["depth_rel"] = float(np.median(np.abs(X[:, 2] / r.scale - d) / d))
            entry["points"] = len(X)
            reproj.append(e)
            rels.append(np.abs(X[:, 2] / r.scale - d) / d)
        r.per_frame.append(entry)
    size = max(max((np.linalg.norm(np.linalg.inv(np.linalg.inv(v.T_world_cam) @ T0)[:3, 3]) for v in views),
                   default=0.0), 1e-9)
    r.rotation_deg = max(e["rotation_deg"] for e in r.per_frame)
    r.translation_rel = max(e["translation"] for e in r.per_frame) / size
    r.focal_rel = max(e["focal_rel"] for e in r.per_frame)
    r.principal_px = max(e["principal_px"] for e in r.per_frame)
    r.reprojection_px = float(np.concatenate(reproj).max()) if reproj else float("nan")
    r.depth_rel = float(np.median(np.concatenate(rels))) if rels else float("nan")
    r.points = int(sum(len(e) for e in reproj))
    return r
