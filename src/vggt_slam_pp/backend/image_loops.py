"""Loops found from images, for sparse backbones (issue 18; our decision, the paper registers dense
VGGT submaps by their points).

A sparse backbone (``colmap``) triangulates only the features it matched within a submap, so two submaps
that see the same place from a few metres apart share few 3-D points (the castle walk's closing pair:
structure overlap 0.09 at the true alignment): registering their points cannot verify the loop. Their
*images* can, as offline structure-from-motion closes such a loop. The backbone keeps each submap's
feature database (keypoints, descriptors, matches within the submap, its final camera;
:meth:`~vggt_slam_pp.backend.store.SubmapStore.put_features`), and a candidate is registered by:

1. merging the two databases (``pycolmap.Database.merge``) and matching only the image pairs across the
   two submaps (SIFT, COLMAP's geometric verification): at least ``min_cross_inliers`` verified matches;
2. a model of the match submap alone (its keyframes held at their own poses, its points triangulated
   from its own matches), into which COLMAP's incremental mapper registers the query's keyframes
   (``fix_existing_frames``): at least ``min_images`` of them;
3. the similarity that takes the query's own cameras onto their registered poses is ``T_match_query``
   (:func:`fit_similarity`); its RMS camera-centre residual must stay below ``max_centre_residual`` of
   the cameras' spread (the registration agrees with the query's own reconstruction), and it sets the
   loop's information (rotation and log-scale sigma = the relative residual, at least ``min_sigma``;
   translation sigma = that times the cameras' spread), taken where the two submaps see each other and moved
   to the query's origin by the lever arm (:func:`image_loop_information`). On the castle walk's closing
   loop this placed the last submap against the first with half the error of the chained odometry (0.053
   against 0.110 m over the two submaps' cameras); a joint reconstruction of both submaps, each fitted to
   it, gave 0.090 m (its relative scale 1.3 % off).

The loop then goes through the same bounds and acceptance as a point registration
(:mod:`vggt_slam_pp.backend.loops`). One candidate costs a few seconds on a CPU (matching 64 image pairs
and registering 8 images), so only the best ``max_candidates`` of a query are registered this way.
"""

from __future__ import annotations

import logging
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from vggt_slam_pp.backend.registration import LoopBounds, LoopResult, correction_size
from vggt_slam_pp.backend.store import SubmapStore
from vggt_slam_pp.geometry.alignment import umeyama
from vggt_slam_pp.geometry.lie import decompose_sim3, make_sim3, sim3_covariance_at_origin, sim3_inverse

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ImageLoopConfig:
    enabled: bool = True  # used whenever both submaps have a feature database (sparse backbones)
    max_candidates: int = 2  # per query: the best candidates by place recognition (proximity ones after)
    min_images: int = 3  # of the query's keyframes registered into the match
    min_cross_inliers: int = 30  # verified matches between the two submaps' images, summed over pairs
    max_centre_residual: float = 0.05  # RMS camera-centre residual of the fits / the cameras' RMS spread
    threads: int = 1  # matching and mapping (1: the same result every run)
    min_sigma: float = 0.01  # floor of a loop's rotation (rad) and log-scale sigma, and of its relative residual


def fit_similarity(T_a_cam: np.ndarray, T_b_cam: np.ndarray, min_width: float = 0.1) -> tuple[np.ndarray, float]:
    """The similarity ``T_b_a`` [4,4] with ``T_b_cam[k] ~ T_b_a T_a_cam[k]`` for the cameras ``T_*_cam``
    [K,4,4] (camera-to-frame, K >= 2 with distinct centres) of the same images in two frames. From the
    camera centres alone (Umeyama) when they span a plane (second principal extent at least ``min_width``
    of the first): measured on the castle walk's closing loop, the cameras' orientations agreed 10x less
    well between two reconstructions than their centres (1.5 against 0.1 deg). Along a line the rotation
    about it comes from the orientations, averaged over the cameras, and scale and shift from the centres.
    Returns it and the RMS centre residual relative to the centres' RMS spread in frame b."""
    ca, cb = T_a_cam[:, :3, 3], T_b_cam[:, :3, 3]
    da, db = ca - ca.mean(0), cb - cb.mean(0)
    sv = np.linalg.svd(da, compute_uv=False)
    if len(ca) >= 3 and sv[1] >= min_width * sv[0]:
        T = umeyama(ca, cb, with_scale=True)
        s, R, _ = decompose_sim3(T)
    else:
        R = np.zeros((3, 3))
        for A, B in zip(T_a_cam, T_b_cam, strict=True):
            _, Ra, _ = decompose_sim3(A)
            _, Rb, _ = decompose_sim3(B)
            R += Rb @ Ra.T
        U, _, Vt = np.linalg.svd(R)
        R = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
        ra = da @ R.T
        s = float(np.sum(ra * db) / max(np.sum(ra * ra), 1e-12))
    t = cb.mean(0) - s * R @ ca.mean(0)
    spread = float(np.sqrt(np.mean(np.sum(db**2, axis=1))))
    resid = float(np.sqrt(np.mean(np.sum((db - s * da @ R.T) ** 2, axis=1))))
    return make_sim3(s, R, t), resid / max(spread, 1e-12)


def image_loop_information(rel: float, centres: np.ndarray, linked: np.ndarray) -> np.ndarray:
    """The information [7,7] (``[omega, u, sigma]``, query frame and units, as the graph's loop edge) of an image
    loop whose fit agrees with the query's own cameras to ``rel`` of their spread; ``centres`` [K,3]: the
    query's registered cameras in its own frame, ``linked`` [K]: each one's verified matches with the match
    submap's images.

    The registration is known best where the two submaps see each other: at the centroid of the query's
    cameras weighted by their matches across (all alike when none has any). There the rotation and log-scale
    sigma is ``rel`` and the translation sigma ``rel`` times the cameras' spread; the edge's frame origin (the
    query's first keyframe) lies a lever arm away, so its translation is less certain, and correlated with the
    rotation and scale (:func:`~vggt_slam_pp.geometry.lie.sim3_covariance_at_origin`), as a point registration's
    information is taken about the ICP's centre (``registration.loop_information``). Castle walk's closing loop:
    query keyframes 26-29 see the match, the origin is keyframe 22 (docs/backend.md)."""
    w = linked if linked.sum() > 0 else np.ones(len(centres))
    c = (w[:, None] * centres).sum(axis=0) / w.sum()
    spread = float(np.sqrt(np.mean(np.sum((centres - centres.mean(axis=0)) ** 2, axis=1))))
    cov = np.diag(np.r_[[rel] * 3, [rel * spread] * 3, rel] ** 2)
    return np.linalg.inv(sim3_covariance_at_origin(cov, c))


def _anchor(database_path: Path, cams: dict[str, np.ndarray], names: dict, work: Path) -> Path:
    """A COLMAP model of the match submap alone: its registered keyframes at their own poses (submap frame),
    its points triangulated from its matches in ``database_path``; written to ``work/anchor``."""
    import pycolmap

    database = pycolmap.Database.open(database_path)
    try:
        rec = pycolmap.Reconstruction()
        for cam in database.read_all_cameras():
            rec.add_camera_with_trivial_rig(cam)
        for img in database.read_all_images():
            side, k = names.get(img.name, (None, None))
            if side != "match":
                continue
            keypoints = np.asarray(database.read_keypoints(img.image_id), np.float64)[:, :2]
            T = np.asarray(cams["T_cam_submap"][k], np.float64)
            s, R, t = decompose_sim3(T)
            pose = pycolmap.Rigid3d(np.c_[R, t / s])  # a similarity's camera scaled by 1 / s: the same image
            rec.add_image_with_trivial_frame(pycolmap.Image(name=img.name, keypoints=keypoints, camera_id=img.camera_id,
                                                            image_id=img.image_id), pose)
    finally:
        database.close()
    out = work / "anchor"
    out.mkdir()
    pycolmap.triangulate_points(rec, database_path, work, out)
    return out


def _match_across(db_q: Path, db_m: Path, work: Path, config: ImageLoopConfig
                  ) -> tuple[Path, int, dict[str, int]] | None:
    """Merge the two submaps' databases into ``work/joint.db`` and match the image pairs across them; returns
    it, the verified matches across and those matches per image (by name), or None when the two hold an
    image of the same name (a keyframe in both submaps, cut-off frames included)."""
    import pycolmap

    names = []
    for db in (db_q, db_m):
        d = pycolmap.Database.open(db)
        try:
            names.append({im.name for im in d.read_all_images()})
        finally:
            d.close()
    q_names, m_names = names
    if q_names & m_names:
        return None
    merged = work / "joint.db"
    opened = []
    try:
        for path in (db_q, db_m, merged):
            opened.append(pycolmap.Database.open(path))
        pycolmap.Database.merge(*opened)
        images = {im.image_id: im.name for im in opened[2].read_all_images()}
    finally:
        for d in opened:
            d.close()
    pairs = [(x, y) for x in images.values() if x in q_names for y in images.values() if y in m_names]
    (work / "pairs.txt").write_text("".join(f"{x} {y}\n" for x, y in pairs))
    matching = pycolmap.FeatureMatchingOptions()
    matching.use_gpu = False
    matching.num_threads = config.threads
    pairing = pycolmap.ImportedPairingOptions()
    pairing.match_list_path = str(work / "pairs.txt")
    pycolmap.match_image_pairs(merged, matching_options=matching, pairing_options=pairing, device=pycolmap.Device.cpu)
    database = pycolmap.Database.open(merged)
    try:
        pair_ids, geoms = database.read_two_view_geometries()
    finally:
        database.close()
    per_image: dict[str, int] = {}
    for pid, geom in zip(pair_ids, geoms, strict=True):
        i, j = pycolmap.pair_id_to_image_pair(pid)
        if (images.get(i) in q_names) != (images.get(j) in q_names):
            for name in (images[i], images[j]):
                per_image[name] = per_image.get(name, 0) + len(geom.inlier_matches)
    return merged, sum(n for name, n in per_image.items() if name in q_names), per_image


def _cameras(store: SubmapStore, sid: int) -> tuple[Path, dict[str, np.ndarray]] | None:
    found = store.get_features(sid)
    if found is None or not np.isfinite(found[1]["T_cam_submap"]).all():
        return None
    return found


def available(store: SubmapStore, query: int, match: int) -> bool:
    """Whether both submaps have what an image registration needs."""
    return _cameras(store, query) is not None and _cameras(store, match) is not None


def register_by_images(query: int, match: int, store: SubmapStore, T_world_query: np.ndarray,
                       T_world_match: np.ndarray, bounds: LoopBounds, config: ImageLoopConfig,
                       score: float = 0.0, slack: float = 0.0) -> LoopResult:
    """Register loop candidate ``query`` -> ``match`` from their images (module docstring). The current
    estimate (``T_world_*``) is used only to measure the correction against ``bounds`` (world units;
    ``slack`` added to the translation)."""
    import pycolmap

    if not log.isEnabledFor(logging.DEBUG):  # COLMAP's own (glog) chatter only when debugging
        pycolmap.logging.minloglevel = 2

    def reject(reason: str, **kw) -> LoopResult:
        base = dict(T_match_query=None, correction=None, overlap=0.0, structure_overlap=0.0, residual=np.inf,
                    planar_inliers=0, score=score, guess="images")
        base.update(kw)
        return LoopResult(query, match, False, reason, **base)

    found_q, found_m = _cameras(store, query), _cameras(store, match)
    if found_q is None or found_m is None:
        return reject("no image features")
    (db_q, cams_q), (db_m, cams_m) = found_q, found_m
    names = {}
    for side, cams in (("query", cams_q), ("match", cams_m)):
        for k, (i, ok) in enumerate(zip(cams["frame_indices"], cams["valid"], strict=True)):
            if ok:
                names[f"{int(i):08d}.png"] = (side, k)
    work = Path(tempfile.mkdtemp(prefix="vggt_slam_imageloop_"))
    try:
        try:
            found = _match_across(db_q, db_m, work, config)
        except Exception as exc:  # noqa: BLE001 - pycolmap raises plain runtime and value errors
            return reject(f"images: matching across failed ({exc})")
        if found is None:
            return reject("the two submaps share keyframes")
        merged, cross, per_image = found
        if cross < config.min_cross_inliers:
            return reject(f"images: {cross} verified matches between the two submaps < {config.min_cross_inliers}",
                          planar_inliers=cross)
        opts = pycolmap.IncrementalPipelineOptions()
        opts.num_threads = config.threads
        opts.random_seed = 0
        opts.multiple_models = False
        opts.ba_refine_focal_length = False
        opts.ba_refine_principal_point = False
        opts.ba_refine_extra_params = False
        opts.fix_existing_frames = True
        (work / "sparse").mkdir()
        try:
            recs = pycolmap.incremental_mapping(merged, work, work / "sparse", options=opts,
                                                input_path=_anchor(merged, cams_m, names, work))
        except Exception as exc:  # noqa: BLE001 - pycolmap raises plain runtime errors
            return reject(f"images: registration into the match failed ({exc})", planar_inliers=cross)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    if not recs:
        return reject("images: no registration into the match", planar_inliers=cross)
    rec = max(recs.values(), key=lambda r: r.num_reg_images())
    # per side: each registered keyframe's camera in its own submap's frame, and in the model (match frame)
    placed = {"query": ([], []), "match": ([], [])}
    linked = []  # per registered query keyframe: its verified matches with the match submap's images
    for img in rec.images.values():
        if img.has_pose and img.name in names:
            side, k = names[img.name]
            cams = cams_q if side == "query" else cams_m
            placed[side][0].append(sim3_inverse(cams["T_cam_submap"][k]))  # camera -> submap frame
            placed[side][1].append(np.vstack([img.cam_from_world().inverse().matrix(), [0, 0, 0, 1]]))
            if side == "query":
                linked.append(per_image.get(img.name, 0))
    n_q, n_m = len(placed["query"][0]), len(placed["match"][0])
    n_valid_q, n_valid_m = int(cams_q["valid"].sum()), int(cams_m["valid"].sum())
    kw = dict(overlap=n_q / max(n_valid_q, 1), structure_overlap=n_m / max(n_valid_m, 1), planar_inliers=cross)
    if min(n_q, n_m) < config.min_images:
        return reject(f"images: {n_q} query and {n_m} match keyframes registered < {config.min_images}", **kw)
    (own_q, model_q), (own_m, model_m) = ((np.array(a), np.array(b)) for a, b in (placed["query"], placed["match"]))
    T_M_q, res_q = fit_similarity(own_q, model_q)
    T_M_m, res_m = fit_similarity(own_m, model_m)
    Z = sim3_inverse(T_M_m) @ T_M_q  # T_match_query (T_M_m: the identity up to rounding, the match held fixed)
    worst = max(res_q, res_m)  # relative to the cameras' spread
    s_m, _, _ = decompose_sim3(T_world_match)
    spread_m = float(np.sqrt(np.mean(np.sum((own_m[:, :3, 3] - own_m[:, :3, 3].mean(0)) ** 2, axis=1))))
    kw.update(residual=worst * spread_m * float(s_m), agreement=1.0 - worst, agreement_cells=cross)  # world units
    if worst > config.max_centre_residual:
        return reject(f"images: the registration disagrees with the submaps' cameras (residual {worst:.3f} "
                      f"of their spread > {config.max_centre_residual})", **kw)
    C = T_world_match @ Z @ sim3_inverse(T_world_query)
    centre = (T_world_query @ np.r_[own_q[:, :3, 3].mean(0), 1.0])[:3]
    log_s, turned, moved = correction_size(C, centre)
    if log_s > bounds.max_log_scale:
        return reject(f"scale change x{np.exp(log_s):.2f} beyond what odometry allows (x{np.exp(bounds.max_log_scale):.2f})",
                      **kw)
    if moved > bounds.max_translation + slack:
        return reject(f"moves the submap {moved:.1f} > {bounds.max_translation:.1f} that odometry allows", **kw)
    if turned > bounds.max_yaw_deg:
        return reject(f"turns the submap {turned:.0f} deg > {bounds.max_yaw_deg:.0f} that odometry allows", **kw)
    kw["information"] = image_loop_information(max(worst, config.min_sigma), own_q[:, :3, 3],
                                                np.array(linked, float))
    log.info("loop %d->%d from images: %d / %d keyframes registered, %d matches across, residual %.3f",
             query, match, n_q, n_m, cross, worst)
    return LoopResult(query, match, True, "accepted", Z, C, score=score, guess="images", **kw)
