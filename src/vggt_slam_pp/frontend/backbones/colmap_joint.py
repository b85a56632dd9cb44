"""The link between two consecutive COLMAP submaps from one bundle adjustment of both.

Each submap is reconstructed on its own, and each drifts inside itself a little (most at its ends). The
shared keyframes measure the link only where the previous submap ends, so its end's drift goes into the
edge. Here the two reconstructions are joined into one model: the shared keyframes become one image, a
keypoint seen in both submaps one track, and one bundle adjustment (intrinsics held) makes the joint
model consistent over both submaps' keyframes. Each submap is then placed on the joint model by all of
its cameras (rotation from the orientations, scale and translation from the centres), and the link is
the composition of the two placements. The link does not depend on the joint model's gauge.

The two submaps' features of a shared image are the same: COLMAP extracts them per image,
deterministically, with the same options (checked; the link is not computed otherwise).
"""

from __future__ import annotations

import logging

import numpy as np

from vggt_slam_pp.geometry import make_sim3, sim3_inverse
from vggt_slam_pp.geometry.alignment import estimate_sim3_robust

log = logging.getLogger(__name__)

MIN_SHARED_POINTS = 20
# ``auto``: the joint link is used unless the cameras move along their optical axes (the median |cos| of the angle
# between a camera's axis and its step to the next camera at least this): the joint model of two forward-motion
# submaps drifts in scale more than their junction does (docs/frontend.md, "The joint link"); measured 0.43-0.76
# on EuRoC, 0.26-0.55 on the castle walk, 0.99-1.00 on every rendered forward-motion sequence
FORWARD_MOTION_COS = 0.9  # keypoints seen in both submaps (as 3-D points) needed for a starting alignment


def _pose(image) -> np.ndarray:
    """[4,4] cam_from_world of a pycolmap image."""
    return np.vstack([image.cam_from_world().matrix(), [0.0, 0.0, 0.0, 1.0]])


def _keypoints(image) -> np.ndarray:
    return np.array([p.xy for p in image.points2D], dtype=np.float64).reshape(-1, 2)


def placement(T_cam_from: dict[str, np.ndarray], T_cam_to: dict[str, np.ndarray]) -> np.ndarray | None:
    """Sim(3) ``T_to_from`` that best places the cameras of frame "from" on the same cameras in frame
    "to" (dicts name -> [4,4] cam_from_frame): rotation averaged from the orientations, then scale and
    translation by least squares on the centres. None with fewer than two cameras or no spread."""
    names = [n for n in T_cam_from if n in T_cam_to]
    if len(names) < 2:
        return None
    Rs = np.array([T_cam_to[n][:3, :3].T @ T_cam_from[n][:3, :3] for n in names])
    U, _, Vt = np.linalg.svd(Rs.sum(axis=0))
    R = U @ np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))]) @ Vt
    c_from = np.array([-T_cam_from[n][:3, :3].T @ T_cam_from[n][:3, 3] for n in names])
    c_to = np.array([-T_cam_to[n][:3, :3].T @ T_cam_to[n][:3, 3] for n in names])
    a = (c_from - c_from.mean(axis=0)) @ R.T
    b = c_to - c_to.mean(axis=0)
    spread = float((a * a).sum())
    if spread <= 1e-12:
        return None
    s = float((a * b).sum()) / spread
    if not s > 0:
        return None
    t = c_to.mean(axis=0) - s * R @ c_from.mean(axis=0)
    return make_sim3(s, R, t)


def forward_motion(recs, names: list[set[str] | None] | None = None) -> float:
    """The median |cos| of the angle between each camera's optical axis and its step to the next camera (by image
    name) over the reconstructions ``recs`` (each with the names of its images to use, None for all): 1 for a
    camera moving straight ahead (driving), 0 for one moving sideways (a photo walk around a building)."""
    cosines = []
    for k, rec in enumerate(recs):
        kept = None if names is None else names[k]
        images = sorted((im for im in rec.images.values() if im.has_pose and (kept is None or im.name in kept)),
                        key=lambda im: im.name)
        for a, b in zip(images, images[1:], strict=False):
            step = b.projection_center() - a.projection_center()
            norm = float(np.linalg.norm(step))
            if norm > 1e-12:
                cosines.append(abs(float(np.dot(step / norm, a.viewing_direction()))))
    return float(np.median(cosines)) if cosines else float("nan")


def centre_residual(T_to_from: np.ndarray, T_cam_from: dict[str, np.ndarray], T_cam_to: dict[str, np.ndarray]) -> float:
    """RMS distance, in frame "to" units, between the cameras' centres in "to" and their "from" centres
    placed by ``T_to_from``."""
    names = [n for n in T_cam_from if n in T_cam_to]
    c_from = np.array([-T_cam_from[n][:3, :3].T @ T_cam_from[n][:3, 3] for n in names])
    c_to = np.array([-T_cam_to[n][:3, :3].T @ T_cam_to[n][:3, 3] for n in names])
    placed = c_from @ T_to_from[:3, :3].T + T_to_from[:3, 3]
    return float(np.sqrt(np.mean(np.sum((placed - c_to) ** 2, axis=1))))


def joint_link(window: list[tuple[object, set[str] | None]], threads: int = 1
               ) -> tuple[np.ndarray, float, float] | None:
    """Sim(3) ``T_prevworld_currworld`` between the world frames of the last two pycolmap reconstructions of
    ``window`` (consecutive submaps, oldest first, each with the names of the images the front-end kept, None
    for all) from one bundle adjustment of all of them (module docstring), its residual (the RMS distance of
    both submaps' camera centres, placed, from their jointly adjusted centres; prev world units) and that
    residual relative to the cameras' RMS spread about their centroid (the link's relative uncertainty). None when
    they cannot be joined (different cameras, too few shared points, different features of a shared image, a
    failed adjustment)."""
    joined = joint_model(window, threads)
    if joined is None:
        return None
    own, adjusted = joined
    T_joint_prev = placement(own[-2], adjusted[-2])
    T_joint_curr = placement(own[-1], adjusted[-1])
    if T_joint_prev is None or T_joint_curr is None:
        return None
    to_prev = 1.0 / float(np.cbrt(np.linalg.det(T_joint_prev[:3, :3])))  # joint units -> prev world units
    residual = to_prev * float(np.sqrt(np.mean([centre_residual(T_joint_prev, own[-2], adjusted[-2]) ** 2,
                                                centre_residual(T_joint_curr, own[-1], adjusted[-1]) ** 2])))
    spread = to_prev * float(np.sqrt(np.mean([_spread(adjusted[-2]) ** 2, _spread(adjusted[-1]) ** 2])))
    return sim3_inverse(T_joint_prev) @ T_joint_curr, residual, residual / max(spread, 1e-12)


def _spread(T_cam: dict[str, np.ndarray]) -> float:
    """RMS distance of the cameras' centres from their centroid."""
    c = np.array([-T[:3, :3].T @ T[:3, 3] for T in T_cam.values()])
    return float(np.sqrt(np.mean(np.sum((c - c.mean(axis=0)) ** 2, axis=1))))


def _start(prev, P: dict, curr, C: dict) -> np.ndarray | None:
    """A starting Sim(3) ``T_prevworld_currworld`` from the 3-D points both reconstructions have on the
    shared images' keypoints; None with too few or when a shared image's features differ."""
    src, dst = [], []
    for n in [n for n in C if n in P]:
        a, b = _keypoints(P[n]), _keypoints(C[n])
        if a.shape != b.shape or not np.allclose(a, b):
            log.info("joint link: the two submaps' features of %s differ; not joined", n)
            return None
        for k in C[n].get_observation_point2D_idxs():
            pp = P[n].point2D(int(k))
            if pp.has_point3D():
                src.append(curr.point3D(C[n].point2D(int(k)).point3D_id).xyz)
                dst.append(prev.point3D(pp.point3D_id).xyz)
    if len(src) < MIN_SHARED_POINTS:
        return None
    return estimate_sim3_robust(np.array(src), np.array(dst), seed=0).T_dst_src


def joint_model(window: list[tuple[object, set[str] | None]], threads: int = 1):
    """The joint bundle adjustment of :func:`joint_link`: (each reconstruction's own poses, the same
    images' poses in the joint model), two lists of dicts image name -> [4,4] cam_from_world in window
    order; None when the reconstructions cannot be joined.

    An image held by several reconstructions is one image of the joint model (the oldest's pose to start).
    A 3-D point of a later reconstruction on a keypoint that is a point of an earlier one is the same point,
    merged where the association is one-to-one (two reconstructions can split or join tracks differently);
    the others keep their own observations that no earlier point holds."""
    import pycolmap

    images = [{im.name: im for im in sorted(rec.images.values(), key=lambda im: im.name)
               if im.has_pose and (names is None or im.name in names)} for rec, names in window]
    if len(window) < 2 or any(len(kept) < 2 for kept in images):
        return None
    cameras = [next(iter(rec.cameras.values())) for rec, _ in window]
    if any(c.model != cameras[0].model or not np.allclose(c.params, cameras[0].params, rtol=1e-6, atol=1e-9)
           for c in cameras[1:]):
        # a shared image is one image of the joint model, seen through one camera: submaps estimated with
        # different cameras (the held camera refined on a later submap) would see it differently
        log.info("joint link: the submaps' cameras differ; linked by the shared keyframes alone")
        return None
    starts = [np.eye(4)]  # T_firstworld_world of each reconstruction
    for k in range(1, len(window)):
        T = _start(window[k - 1][0], images[k - 1], window[k][0], images[k])
        if T is None:
            return None
        starts.append(starts[-1] @ T)

    joint = pycolmap.Reconstruction()
    ids: dict[str, int] = {}  # image name -> joint image id
    cam = cameras[0]
    joint.add_camera_with_trivial_rig(pycolmap.Camera(model=cam.model, width=cam.width, height=cam.height,
                                                      params=cam.params, camera_id=1))
    for k, kept in enumerate(images):
        for n, im in kept.items():
            if n in ids:
                continue
            T = _pose(im) @ sim3_inverse(starts[k])  # cam_from_firstworld, up to scale: made rigid
            T[:3, :] /= np.cbrt(np.linalg.det(T[:3, :3]))
            T[3] = [0.0, 0.0, 0.0, 1.0]
            ids[n] = len(ids) + 1
            joint.add_image_with_trivial_frame(
                pycolmap.Image(name=n, keypoints=_keypoints(im), camera_id=1, image_id=ids[n]),
                pycolmap.Rigid3d(pycolmap.Rotation3d(T[:3, :3]), T[:3, 3]))

    def add(xyz, elements, color) -> int:
        track = pycolmap.Track()
        for i, kp in elements:
            track.add_element(i, kp)
        return joint.add_point3D(xyz, track, color)

    owner: dict[tuple[int, int], int] = {}  # (joint image id, keypoint) -> joint point
    for k, ((rec, _), kept) in enumerate(zip(window, images, strict=True)):
        points = [(point, [(ids[rec.image(e.image_id).name], int(e.point2D_idx)) for e in point.track.elements
                           if rec.image(e.image_id).name in kept]) for point in rec.points3D.values()]
        links = [{owner[e] for e in elements if e in owner} for _, elements in points]
        claims: dict[int, int] = {}
        for linked in links:
            for pid in linked:
                claims[pid] = claims.get(pid, 0) + 1
        added: dict[tuple[int, int], int] = {}
        for (point, elements), linked in zip(points, links, strict=True):
            free = [e for e in elements if e not in owner]
            if len(linked) == 1 and claims[next(iter(linked))] == 1:
                pid = next(iter(linked))
                seen = {e.image_id for e in joint.point3D(pid).track.elements}
                for i, kp in free:
                    if i not in seen:
                        joint.add_observation(pid, pycolmap.TrackElement(i, kp))
                        added[(i, kp)] = pid
            elif len(free) >= 2:
                pid = add(starts[k][:3, :3] @ point.xyz + starts[k][:3, 3], free, point.color)
                added.update({e: pid for e in free})
        owner.update(added)
    ba = pycolmap.BundleAdjustmentOptions()
    ba.refine_focal_length = ba.refine_principal_point = ba.refine_extra_params = False
    ba.print_summary = False
    ba.ceres.solver_options.num_threads = threads
    config = pycolmap.BundleAdjustmentConfig()
    for image_id in joint.reg_image_ids():
        config.add_image(image_id)
    for camera_id in joint.cameras:
        config.set_constant_cam_intrinsics(camera_id)
    config.fix_gauge(pycolmap.BundleAdjustmentGauge.TWO_CAMS_FROM_WORLD)  # the link does not depend on it
    try:  # the adjuster, unlike pycolmap.bundle_adjustment, leaves COLMAP's log level alone
        pycolmap.create_default_bundle_adjuster(ba, config, joint).solve()
    except Exception as exc:  # noqa: BLE001 - pycolmap raises plain runtime errors
        log.warning("joint link: bundle adjustment failed (%s)", exc)
        return None
    log.debug("joint link: %d reconstructions, %d images, %d points", len(window), len(ids), joint.num_points3D())
    own = [{n: _pose(im) for n, im in kept.items()} for kept in images]
    return own, [{n: _pose(joint.image(ids[n])) for n in kept} for kept in images]
