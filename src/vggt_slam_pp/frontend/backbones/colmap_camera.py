"""The shared camera of uncalibrated COLMAP submaps: its models, their sanity bounds, and the starting values of
one model from another (``colmap.py`` estimates and holds the camera; docs/frontend.md, "Camera (uncalibrated)").

Models (COLMAP's parameter order), in two families, each with a constrained model (one focal length, two radial
terms, the principal point at the image centre) and the full one it is refined to:

* ``RADIAL`` (f, cx, cy, k1, k2) -> ``OPENCV`` (fx, fy, cx, cy, k1, k2, p1, p2): radial distortion polynomial in
  the undistorted radius ``r``, ``r_d = r (1 + k1 r^2 + k2 r^4)``, plus tangential terms;
* ``RADIAL_FISHEYE`` (f, cx, cy, k1, k2) -> ``OPENCV_FISHEYE`` (fx, fy, cx, cy, k1, k2, k3, k4): polynomial in the
  ray's angle ``t = atan(r)``, ``r_d = t (1 + k1 t^2 + k2 t^4 + k3 t^6 + k4 t^8)``.

The two full models have the same number of parameters. The equidistant one also represents a plain pinhole
(``tan``'s series) and fits the edges of wide lenses that the polynomial in ``r`` does not: EuRoC's 752 x 480
camera (about 79 deg across), first submap, mean reprojection error 0.48 -> 0.41 px and focal length 2.6 % ->
0.7 % long.
"""

from __future__ import annotations

import numpy as np

# how far the full camera model may move from the constrained estimate it is refined from (``_full_model``):
# focal lengths (relative), their ratio, and the principal point from the image centre (fraction of each side)
FULL_MODEL_TOLERANCE = {"focal": 0.05, "aspect": 0.03, "principal_point": 0.05}

# the full models an estimate is refined to, each from its family's constrained model; the first is the
# default, another replaces it only when its mean reprojection error is lower by at least
# ``MODEL_CHOICE_MARGIN`` (relative): both have eight parameters, so the lower error is the better model, and the
# margin keeps the default where the two fit alike (a pinhole)
FULL_MODELS = ("OPENCV", "OPENCV_FISHEYE")
CONSTRAINED = {"OPENCV": "RADIAL", "OPENCV_FISHEYE": "RADIAL_FISHEYE"}
_FULL = {constrained: full for full, constrained in CONSTRAINED.items()}
MODEL_CHOICE_MARGIN = 0.05


def far_from(params: list[float], f: float, width: int, height: int) -> str:
    """Why full-model ``params`` (fx, fy, cx, cy first) are too far from a constrained estimate with focal ``f``
    (FULL_MODEL_TOLERANCE), or ""."""
    fx, fy, cx, cy = params[:4]
    tol = FULL_MODEL_TOLERANCE
    if abs(0.5 * (fx + fy) / f - 1) > tol["focal"]:
        return f"focal {0.5 * (fx + fy):.1f} px, {f:.1f} px constrained"
    if abs(fx / fy - 1) > tol["aspect"]:
        return f"focal lengths {fx:.1f} and {fy:.1f} px"
    if abs(cx - width / 2) > tol["principal_point"] * width or abs(cy - height / 2) > tol["principal_point"] * height:
        return f"principal point ({cx:.0f}, {cy:.0f}) moved from the centre"
    return ""


def _radial_map(model: str, k: list[float], r: np.ndarray) -> np.ndarray:
    """The distorted normalised radius at undistorted radii ``r`` (tangential terms aside)."""
    if model == "OPENCV_FISHEYE":
        t = np.arctan(r)
        t2 = t * t
        return t * (1 + t2 * (k[0] + t2 * (k[1] + t2 * (k[2] + t2 * k[3]))))
    r2 = r * r
    return r * (1 + r2 * (k[0] + r2 * k[1]))


def _undistorted_reach(model: str, k: list[float], r_d: float) -> float | None:
    """The undistorted radius whose distorted radius is ``r_d``, along the branch where the mapping still
    grows; None when the mapping turns back before reaching it (the lens would fold the image's edge back)."""
    r = np.linspace(0.0, 20.0, 4001)[1:]  # up to 87 deg off the axis
    d = _radial_map(model, k, r)
    rising = np.diff(d, prepend=0.0) > 0
    stop = len(r) if rising.all() else int(np.argmin(rising))
    reach = np.flatnonzero(d[:stop] >= r_d)
    return float(r[reach[0]]) if len(reach) else None


def intrinsics_sane(params, width: int, height: int, model: str = "OPENCV") -> str:
    """Why ``params`` of a ``model`` camera (either family's) are implausible for a ``width`` x ``height`` image,
    or "" when they are sensible: focal 0.3-4x the larger side, fx / fy within 10 %, principal point in the middle
    40 %, distortion terms below 1 (tangential below 0.05), and a radial mapping that keeps growing out to the
    image's corners."""
    values = [float(v) for v in params]
    if model in ("RADIAL", "RADIAL_FISHEYE"):
        values, model = full_start(values), _FULL[model]
    fx, fy, cx, cy = values[:4]
    side = max(width, height)
    if not 0.3 * side <= fx <= 4 * side or not 0.3 * side <= fy <= 4 * side:
        return f"focal length {fx:.0f}/{fy:.0f} px outside 0.3-4x the image side ({side} px)"
    if abs(fx / fy - 1) > 0.1:
        return f"focal lengths {fx:.0f} and {fy:.0f} px differ by more than 10 %"
    if not (0.3 * width <= cx <= 0.7 * width and 0.3 * height <= cy <= 0.7 * height):
        return f"principal point ({cx:.0f}, {cy:.0f}) far from the image centre"
    k = values[4:8]
    radial = k if model == "OPENCV_FISHEYE" else k[:2]
    tangential = [] if model == "OPENCV_FISHEYE" else k[2:]
    if any(abs(v) >= 1 for v in radial) or any(abs(v) >= 0.05 for v in tangential):
        return "distortion (" + ", ".join(f"{v:.3g}" for v in k) + ") out of bounds"
    corner = np.hypot(max(cx, width - cx) / fx, max(cy, height - cy) / fy)
    if _undistorted_reach(model, radial + [0.0] * (4 - len(radial)), corner) is None:
        return "distortion (" + ", ".join(f"{v:.3g}" for v in k) + ") folds back inside the image"
    return ""


def constrained_start(model: str, f: float, cx: float, cy: float, k1: float, k2: float, width: int,
                      height: int) -> list[float]:
    """Starting values of a constrained ``model`` camera (``RADIAL`` or ``RADIAL_FISHEYE``) with the projection
    of a ``RADIAL`` one (f, cx, cy, k1, k2): the equidistant terms are fitted by least squares to the same radial
    mapping over the image, out to its corners."""
    if model == "RADIAL":
        return [f, cx, cy, k1, k2]
    if model != "RADIAL_FISHEYE":
        raise ValueError(f"no starting values for a {model} camera")
    corner = np.hypot(max(cx, width - cx), max(cy, height - cy)) / f
    reach = _undistorted_reach("OPENCV", [k1, k2, 0.0, 0.0], corner) or corner
    r = np.linspace(reach / 200, reach, 200)
    t = np.arctan(r)
    A = np.stack([t ** 3, t ** 5], axis=1)
    k = np.linalg.lstsq(A, _radial_map("OPENCV", [k1, k2, 0.0, 0.0], r) - t, rcond=None)[0]
    return [f, cx, cy, float(k[0]), float(k[1])]


def full_start(params: list[float]) -> list[float]:
    """The full model's parameters with the same projection as a constrained model's ``params`` (f, cx, cy, k1,
    k2), in either family: fx = fy = f, the other two terms 0."""
    f, cx, cy, k1, k2 = (float(v) for v in params)
    return [f, f, cx, cy, k1, k2, 0.0, 0.0]


def parameter_names(model: str) -> str:
    """The parameters of a ``model`` camera, in order, for people."""
    return {"RADIAL": "f cx cy k1 k2", "RADIAL_FISHEYE": "f cx cy k1 k2",
            "OPENCV_FISHEYE": "fx fy cx cy k1 k2 k3 k4"}.get(model, "fx fy cx cy k1 k2 p1 p2")
