"""Weight-free CPU backbone: per-submap structure-from-motion with pycolmap.

For each submap the keyframes are written to a temporary folder, SIFT features are extracted (one
shared camera), matched, and reconstructed by COLMAP's global mapper (GLOMAP: rotation averaging over
the verified keyframe pairs, global positioning, bundle adjustment; ``mapper="global"``, default) or
registered into the previous submap by the incremental mapper (``mapper="incremental"``, anchored).
docs/frontend.md ("Chaining COLMAP submaps") has the measurements behind the default.

Matching: all pairs within the submap (``matcher="exhaustive"``, default) or sequential with an
``overlap`` of 10 (``"sequential"``, the SPEC's wording). A submap has only 33-40 images (528-780 pairs), and
on the EuRoC excerpt all-pairs matching lowered the odometry ATE from 0.057 to 0.048 m (calibrated)
and from 0.080 to 0.077 m (uncalibrated) for about 35 % more time, so it is the default.

* Uncalibrated (default): a shared ``OPENCV`` or ``OPENCV_FISHEYE`` camera (``SIMPLE_RADIAL`` fails on the
  EuRoC lens, SPEC 3.3), estimated on the first submap that reconstructs and then held fixed
  (``freeze_estimated``; per-submap estimates change the focal length, hence the scale, from submap to
  submap). It is estimated in two stages: mapped with a ``RADIAL`` camera (one focal length, two radial
  terms, principal point at the image centre), then, in each family of ``colmap_camera``, refined to the
  full model by one bundle adjustment, kept only when it stays near its constrained estimate
  (``FULL_MODEL_TOLERANCE``); the family whose model explains the images better is kept (``_full_model``).
  Eight free intrinsics on a forward drive gave fx 416 / fy 652 px. Forward motion hardly constrains the
  focal length, rotation does: a later sound submap that turns at least twice as much as the one the camera
  came from refines an ``OPENCV`` camera (``_refocus``).
  When every attempt with the held camera is folded (below) or registers fewer than half the frames,
  the submap is mapped again with the camera estimated, and a sane estimate from a fold-free
  reconstruction replaces the held one.
* Calibrated: the dataset's intrinsics and distortion are given to the camera and kept fixed.

The submap frame is frame 0's camera (COLMAP's arbitrary world is moved there, after scaling it so that
the camera centres' 10th-90th percentile extent is 10 units). Observations are the triangulated
keypoints of each image: ``keys`` are SIFT keypoint indices, identical for the same image in two
submaps, so the shared keyframes link submaps (odometry method ``pose_scale``; ``anchored`` with the incremental mapper).
With the global mapper the link is ``joint`` (``link`` "joint", or "auto" unless the cameras move ahead): one bundle
adjustment of the previous submap's and this one's reconstructions, each placed on it by all its cameras
(``colmap_joint``; ``info["joint_link"]``).
Confidence per point: ``track_length / (1 + reprojection error)``.

Failures degrade instead of raising. Mapping is retried (``ATTEMPTS``: the global mapper, then the
incremental one with initial triangulation angles 16 -> 4 -> 2 degrees and other seeds) while keyframes
stay unregistered or the reconstruction is *folded*: it contradicts the verified matches of a pair of
consecutive keyframes (``colmap_checks.py``). The attempt kept registers most frames before any
contradicted pair (``_better``). A fold left in every attempt splits the submap there when that keeps
at least its first half (the rest starts the next submap), and is otherwise kept and reported
(``info["folded_pairs"]``).
Frames left unregistered are marked ``valid=False`` with the nearest registered neighbour's pose (the
front-end splits them off or bridges, see ``frontend.py``), and a submap that cannot be reconstructed
at all is returned with every frame invalid (identity poses, no points).

Determinism: feature extraction, matching and mapping run on one thread unless ``deterministic=False``
(multi-threaded, repeated runs of one submap differed by up to 8 cm); the mappers' and the fold check's
random seeds are the run's seed (plus the attempt's offset). docs/frontend.md gives the measured cost.

Estimated intrinsics must be physically sensible (``colmap_camera.intrinsics_sane``); an estimate outside the
bounds is not adopted (logged).
"""

from __future__ import annotations

import logging
import shutil
import tempfile
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import numpy as np

from vggt_slam_pp.frontend.backbones.base import Backbone
from vggt_slam_pp.frontend.backbones.colmap_camera import (
    CONSTRAINED,
    FULL_MODELS,
    MODEL_CHOICE_MARGIN,
    constrained_start,
    far_from,
    full_start,
    intrinsics_sane,
)
from vggt_slam_pp.frontend.backbones.colmap_checks import (
    FoldCheckConfig,
    PairCheck,
    check_pairs,
    inconsistent,
)
from vggt_slam_pp.frontend.backbones.colmap_joint import FORWARD_MOTION_COS, forward_motion, joint_link
from vggt_slam_pp.frontend.types import SubmapPrediction
from vggt_slam_pp.geometry.lie import se3_inverse
from vggt_slam_pp.io.frames import Frame

if TYPE_CHECKING:
    from vggt_slam_pp.io.frames import FrameSource
    from vggt_slam_pp.pipeline import RunConfig

log = logging.getLogger(__name__)

# mapping attempts while keyframes stay unregistered or the reconstruction is folded: (initial triangulation
# angle in degrees, seed offset) of COLMAP's incremental mapper; an angle of None is its global mapper (GLOMAP)
ATTEMPTS = ((16.0, 0), (None, 0), (4.0, 0), (16.0, 1), (2.0, 0), (8.0, 2))


def _describe(folds: list[PairCheck], config: FoldCheckConfig | None = None) -> str:
    config = config or FOLD_CHECK
    bent = [c for c in folds if c.folded(config)]
    cut = [c for c in folds if c.disconnected(config)]
    parts = []
    if bent:
        worst = max(bent, key=lambda c: c.rotation_deg)
        parts.append(f"{len(bent)} keyframe pair(s) from {bent[0].first[:-4]} disagree with their matches, up to "
                     f"{worst.rotation_deg:.1f} deg ({worst.agree:.0%} of matches explained, two-view {worst.best:.0%})")
    if cut:
        c = cut[0]
        parts.append(f"{len(cut)} keyframe pair(s) from {c.first[:-4]} share no structure ({c.shared_points} point(s) "
                     f"for {c.matches} matches, {c.spanning_points} seen on both sides: their distance, hence the "
                     f"scale, is unconstrained)")
    return "; ".join(parts)


def _pair_record(c: PairCheck) -> dict:
    """A contradicted pair for ``report.json`` (NaN, where the pair had no two-view estimate, as None)."""
    def num(v: float, digits: int):
        return round(float(v), digits) if np.isfinite(v) else None
    return {"first": int(c.first[:-4]), "second": int(c.second[:-4]), "agree": num(c.agree, 3),
            "two_view": num(c.best, 3), "rotation_deg": num(c.rotation_deg, 2), "matches": c.matches,
            "shared_points": c.shared_points, "spanning_points": c.spanning_points}


def _sound_images(rec, folds: list[PairCheck]) -> int:
    """Registered images of ``rec`` before its first contradicted pair's second image (all without folds)."""
    names = [im.name for im in rec.images.values() if im.has_pose]
    return sum(n < folds[0].second for n in names) if folds else len(names)


def _better(rec, folds: list[PairCheck], best, best_folds: list[PairCheck]) -> bool:
    """Whether reconstruction ``rec`` beats ``best``: more images registered before any contradicted pair
    (a small fold-free fragment does not beat a whole submap with one late fold), then free of folds, then
    more registered images, then fewer contradicted pairs."""
    def key(r, f):
        return (_sound_images(r, f), not f, r.num_reg_images(), -len(f))
    return key(rec, folds) > key(best, best_folds)


# a held camera is refined on a later sound submap that turns at least ``spread_ratio`` times as much as the
# submap it was estimated on and at least ``min_spread_deg`` (``_view_spread``), and adopted when its focal
# length moves by ``min_change``
REFOCUS = {"spread_ratio": 2.0, "min_spread_deg": 30.0, "min_change": 0.01}


def _view_spread(rec) -> float:
    """The largest angle (degrees) between two registered cameras' optical axes in ``rec``."""
    z = np.array([np.asarray(im.cam_from_world().rotation.matrix())[2] for im in rec.images.values() if im.has_pose])
    if len(z) < 2:
        return 0.0
    return float(np.degrees(np.arccos(np.clip((z @ z.T).min(), -1.0, 1.0))))


FOLD_CHECK = FoldCheckConfig()  # the default check of reconstructions against their matches (colmap_checks.py)

class ColmapBackbone(Backbone):
    name = "colmap"
    dense = False

    def __init__(self, calibrated: bool = False, max_features: int = 4096, overlap: int = 10,
                 num_threads: int = -1, seed: int = 0, keep_workdir: str | Path | None = None,
                 freeze_estimated: bool = True, matcher: str = "exhaustive", deterministic: bool = True,
                 anchored: bool | None = None, max_image_size: int = 1600, refine_principal_point: bool = True,
                 camera_model: str = "OPENCV", fix_anchor: bool = True, keep_features: bool = True,
                 fold_check: FoldCheckConfig | None = FOLD_CHECK, mapper: str = "global",
                 estimate_model: str | None = "RADIAL", link: str = "auto") -> None:
        import weakref

        import pycolmap

        if not log.isEnabledFor(logging.DEBUG):  # COLMAP's own (glog) chatter only when debugging
            pycolmap.logging.minloglevel = 2
        self.calibrated = calibrated
        self.freeze_estimated = freeze_estimated
        if matcher not in ("sequential", "exhaustive"):
            raise ValueError(f"unknown matcher {matcher!r}")
        self.matcher = matcher
        if mapper not in ("incremental", "global"):
            raise ValueError(f"unknown mapper {mapper!r}")
        self.mapper = mapper  # the first attempt of a submap that is not anchored (ATTEMPTS)
        self.max_features = max_features
        self.overlap = overlap
        self.num_threads = num_threads
        self.seed = seed
        self.deterministic = deterministic
        self.anchored = (mapper == "incremental") if anchored is None else anchored  # default: with the incremental mapper
        self.max_image_size = max_image_size
        self.refine_principal_point = refine_principal_point
        self.camera_model = camera_model
        # an unknown camera is first estimated with this constrained model, then refined to ``camera_model``
        # (``_full_model``); None estimates ``camera_model`` directly
        self.estimate_model = estimate_model
        self._staged = False  # whether the submap being reconstructed estimates the camera in two stages
        self.fix_anchor = fix_anchor
        self.fold_check = fold_check  # None: reconstructions are not checked against their matches
        self._folds: list[PairCheck] = []  # the inconsistent pairs of the submap being reconstructed
        self._folded_attempts = 0  # of its mapping attempts, how many were folded
        self._cut: str | None = None  # the image from which a submap folded in every attempt is split off
        self._previous = None  # the last committed reconstruction (pycolmap), the anchor of the next submap
        self._previous_ref: np.ndarray | None = None  # its prediction frame: [4,4] cam_from_world of its first camera
        if link not in ("auto", "shared", "joint"):
            raise ValueError(f"unknown link {link!r}")
        self.link = link  # "joint": link each submap to the previous one by a joint bundle adjustment; "auto": unless
        # the cameras move along their optical axes (colmap_joint.FORWARD_MOTION_COS); "shared": never
        self._previous_names: set[str] = set()  # its images that the front-end kept
        # attempts: (frames, rec, features, [4,4] cam_from_world of the prediction's first camera)
        self._pending: list[tuple[tuple[int, ...], object, str | None, np.ndarray]] = []
        self._anchor_names: list[str] = []  # images of the current submap held fixed from the previous one
        self.keep_workdir = Path(keep_workdir) if keep_workdir else None
        self._count = 0
        # each reconstructed submap's feature database (keypoints, descriptors, its matches and its final
        # camera) is kept for loops found from images (backend/image_loops.py): the front-end hands the
        # committed submap's file to the submap store (``info["features"]``); the rest goes with this folder
        self._features = Path(tempfile.mkdtemp(prefix="vggt_slam_features_")) if keep_features else None
        if self._features is not None:
            weakref.finalize(self, shutil.rmtree, str(self._features), True)
        self._estimated: tuple[tuple[int, int], list[float], str] | None = None  # (size, params, model)
        self.camera: dict = {}  # the shared camera for the report: model, params, source, history
        self._span = (0, 0)  # first and last frame index of the submap being reconstructed

    def committed(self, frame_indices) -> None:
        kept = tuple(int(i) for i in frame_indices)
        chosen = None
        for k in range(len(self._pending) - 1, -1, -1):
            frames, rec, _, ref = self._pending[k]
            if frames[:len(kept)] == kept:
                self._previous, self._previous_ref, chosen = rec, ref, k
                self._previous_names = {f"{i:08d}.png" for i in kept}  # a split-off tail is no anchor
                break
        for k, (_, _, features, _) in enumerate(self._pending):  # the other attempts' features are not needed
            if k != chosen and features is not None:
                Path(features).unlink(missing_ok=True)
        self._pending = []

    def describe(self) -> dict:
        return {"camera": dict(self.camera)} if self.camera else {}

    # -- COLMAP steps ---------------------------------------------------------------------------
    def _camera_options(self, frame: Frame):
        import pycolmap

        reader = pycolmap.ImageReaderOptions()
        reader.camera_model = "OPENCV" if self.calibrated and frame.intrinsics is not None else self.camera_model
        if self.calibrated and frame.intrinsics is not None:
            cam = frame.intrinsics
            dist = list(cam.dist[:4]) if cam.dist is not None else [0.0, 0.0, 0.0, 0.0]
            dist += [0.0] * (4 - len(dist))
            reader.camera_params = ",".join(str(float(v)) for v in [cam.fx, cam.fy, cam.cx, cam.cy, *dist])
        elif self._estimated is not None and self._estimated[0] == (frame.width, frame.height):
            # uncalibrated: start from the intrinsics the previous submap estimated (still refined)
            reader.camera_model = self._estimated[2]
            reader.camera_params = ",".join(str(float(v)) for v in self._estimated[1])
        elif self.estimate_model and self.estimate_model != self.camera_model:
            reader.camera_model = self.estimate_model  # estimated in two stages (_full_model)
            self._staged = True
        return reader

    def _reconstruct(self, work: Path, frames: Sequence[Frame]):
        import pycolmap

        images = work / "images"
        images.mkdir(parents=True)
        names = [f"{f.index:08d}.png" for f in frames]  # by frame index: the same name in every submap
        for name, f in zip(names, frames, strict=True):
            cv2.imwrite(str(images / name), cv2.cvtColor(f.image, cv2.COLOR_RGB2BGR))
        db = work / "database.db"
        self._staged = False
        extraction = pycolmap.FeatureExtractionOptions()
        extraction.use_gpu = False
        extraction.num_threads = 1  # deterministic (module docstring)
        extraction.sift.max_num_features = self.max_features
        extraction.max_image_size = self.max_image_size  # larger photos: SIFT on a downscaled copy
        pycolmap.extract_features(db, images, image_names=names, camera_mode=pycolmap.CameraMode.SINGLE,
                                  reader_options=self._camera_options(frames[0]),
                                  extraction_options=extraction, device=pycolmap.Device.cpu)
        matching = pycolmap.FeatureMatchingOptions()
        matching.use_gpu = False
        matching.num_threads = 1
        if self.matcher == "exhaustive":
            pycolmap.match_exhaustive(db, matching_options=matching, device=pycolmap.Device.cpu)
        else:
            pairing = pycolmap.SequentialPairingOptions()
            pairing.overlap = self.overlap
            pairing.loop_detection = False
            pycolmap.match_sequential(db, matching_options=matching, pairing_options=pairing,
                                      device=pycolmap.Device.cpu)
        given = self.calibrated and frames[0].intrinsics is not None
        best, attempt = None, 0
        refine = not (given or (self.freeze_estimated and self._estimated is not None))
        self._anchor_names, self._folds, self._folded_attempts, self._cut = [], [], 0, None
        if self.anchored and not refine:
            best = self._map_anchored(db, images, work, names)
            if best is not None and best.num_reg_images() == len(frames):
                folds = self._check(best, db)
                if not folds:
                    return best, names
                self._folded_attempts += 1
                log.warning("colmap: the anchored reconstruction of keyframes %d..%d contradicts its own matches "
                            "(%s); mapping the submap on its own", *self._span, _describe(folds, self.fold_check))
            elif best is not None:
                log.info("colmap: anchored mapping registered %d/%d images; mapping the submap on its own",
                         best.num_reg_images(), len(frames))
            best, self._anchor_names = None, []
        best_folds: list[PairCheck] = []
        attempts = ATTEMPTS if self.mapper == "incremental" else ((None, 0),) + tuple(a for a in ATTEMPTS if a[0])
        for angle, seed_offset in attempts:
            rec = self._map(db, images, work / f"sparse{attempt}", angle, seed_offset, attempt, refine)
            attempt += 1
            folds = self._check(rec, db) if rec is not None else []
            self._folded_attempts += bool(folds)
            if rec is not None and (best is None or _better(rec, folds, best, best_folds)):
                best, best_folds = rec, folds
            registered = 0 if best is None else best.num_reg_images()
            if not best_folds and (registered == len(frames) or (attempt >= 2 and registered >= 0.9 * len(frames))):
                break  # a few frames that two attempts could not register are left to the front-end
            how = "global mapper" if angle is None else f"init angle {angle:.0f} deg, seed +{seed_offset}"
            if best_folds:
                log.warning("colmap: keyframes %d..%d reconstructed folded: %s (%s); retrying",
                            *self._span, _describe(best_folds, self.fold_check), how)
            else:
                log.info("colmap: %d/%d images registered (%s); retrying", registered, len(frames), how)
        registered = 0 if best is None else best.num_reg_images()
        collapse = registered < len(frames) / 2
        if not refine and not given and (collapse or best_folds):
            why = "a registration collapse" if collapse else "a fold in every attempt"
            log.warning("colmap: %d/%d images registered%s with the estimated camera held fixed; re-estimating the "
                        "intrinsics", registered, len(frames), ", folded," if best_folds else "")
            rec = self._reestimate(db, images, work / f"sparse{attempt}", attempt)
            folds = self._check(rec, db) if rec is not None else []
            if rec is not None and (best is None or _better(rec, folds, best, best_folds)):
                best, best_folds = rec, folds
                if not folds:  # a camera is taken only from a sound reconstruction
                    self._adopt_camera(rec, len(frames), f"re-estimated after {why}")
        elif self._staged and best is not None:
            best = self._full_model(best)
        elif not refine and not given and best is not None and not best_folds and registered >= 0.9 * len(frames):
            best = self._refocus(best, len(frames))
        if best is not None:
            # COLMAP's scale is arbitrary (the global mapper's and a bundle adjustment's drift far from the
            # incremental mapper's): the camera centres' extent is made 10 units, so that the point filter's
            # distance range (submap units) means the same in every submap
            best.normalize()
        self._folds, self._cut = best_folds, None
        if best_folds:
            # the keyframes from the first contradicted pair on are split off (the front-end starts the next
            # submap with them) when that keeps at least half of the submap; a contradiction in its first half
            # is kept and reported: splitting there would leave almost nothing, and the next submap, starting
            # with the same keyframes, would meet it again
            if names.index(best_folds[0].second) >= len(names) // 2:
                self._cut = best_folds[0].second
            log.warning("colmap: every attempt at keyframes %d..%d is folded (%s); %s", *self._span,
                        _describe(best_folds, self.fold_check),
                        f"the keyframes from {self._cut[:-4]} on are left unregistered" if self._cut
                        else "kept: the contradiction is in the submap's first half")
        return best, names

    def _reestimate(self, db: Path, images: Path, out: Path, attempt: int):
        """Map the submap again with its camera estimated (in two stages when ``estimate_model`` is set),
        starting from the held estimate; the reconstruction or None."""
        import pycolmap

        if self.estimate_model and self.estimate_model != self.camera_model and self._estimated is not None:
            fx, fy, _, _, k1, k2 = self._estimated[1][:6]
            if self._estimated[2] != "OPENCV":  # another model's terms mean something else: start undistorted
                k1 = k2 = 0.0
            database = pycolmap.Database.open(db)
            try:
                cam = database.read_all_cameras()[0]
                cam.model = self.estimate_model
                cam.params = [0.5 * (fx + fy), 0.5 * cam.width, 0.5 * cam.height, k1] + \
                    ([k2] if self.estimate_model == "RADIAL" else [])  # stage 1: principal point at the centre
                cam.has_prior_focal_length = True
                database.update_camera(cam)
            finally:
                database.close()
            self._staged = True
        rec = self._map(db, images, out, None, 0, attempt, True)
        if rec is not None and self._staged:
            rec = self._full_model(rec)
        return rec

    def _full_model(self, rec):
        """Stage 2 of estimating the camera: ``rec`` was mapped with the constrained ``estimate_model`` (one
        focal length, radial distortion, principal point at the image centre). For each family of models
        (``colmap_camera``: ``camera_model`` first) the constrained model is fitted from there (the other
        family's by one bundle adjustment), then the full model from it: one bundle adjustment with every
        intrinsic free, counted when it keeps at least 90 % of the points, does not raise the reprojection error,
        is sane and stays near its constrained estimate (``FULL_MODEL_TOLERANCE``); otherwise the family keeps its
        constrained estimate. ``camera_model``'s family is kept unless another's mean reprojection error is lower
        by ``MODEL_CHOICE_MARGIN``. The result is a reconstruction with a full-model camera."""
        import pycolmap

        cam = next(iter(rec.cameras.values()))
        params = [float(v) for v in cam.params]
        if cam.model.name == "SIMPLE_RADIAL":
            params.append(0.0)
        elif cam.model.name != "RADIAL":
            return rec
        width, height = int(cam.width), int(cam.height)
        before = rec.compute_mean_reprojection_error()
        fits = []  # (full model, its family's result, mean reprojection error over rec's observations)
        for model in (self.camera_model, *(m for m in FULL_MODELS if m != self.camera_model)):
            base, error = rec, before
            if CONSTRAINED[model] != "RADIAL":  # fitted on rec's observations, none dropped: the errors compare
                start = constrained_start(CONSTRAINED[model], *params, width, height)
                found = self._refined(rec, CONSTRAINED[model], start, None, before, refine_principal_point=False,
                                      drop_points=False)
                if found is None:
                    continue
                base, error = found
            constrained = params if base is rec else [float(v) for v in next(iter(base.cameras.values())).params]
            found = self._refined(base, model, full_start(constrained), constrained[0], error)
            if found is None:  # the family keeps its constrained estimate, as the full model
                full = pycolmap.Reconstruction(base)
                fcam = next(iter(full.cameras.values()))
                fcam.model, fcam.params = model, full_start(constrained)
                found = (full, error)
            fits.append((model, *found))
        default = next((c for c in fits if c[0] == self.camera_model), None)
        better = min((c for c in fits if c[0] != self.camera_model), key=lambda c: c[2], default=None)
        use_better = better is not None and (default is None or better[2] < (1 - MODEL_CHOICE_MARGIN) * default[2])
        chosen = better if use_better else default
        log.info("colmap: %s camera from the %s estimate (f %.1f px); reprojection error %s", chosen[0],
                 self.estimate_model, params[0], ", ".join(f"{m} {e:.3f} px" for m, _, e in fits))
        return chosen[1]

    def _refined(self, rec, model: str, start: list[float], f: float | None, before: float,
                 refine_principal_point: bool | None = None, drop_points: bool = True):
        """A copy of ``rec`` with its camera made ``model`` at ``start`` and refined by one bundle adjustment
        (``_full_model``), with its mean reprojection error over ``rec``'s observations, or None when that fails
        or is not kept (logged): the error above ``before``, insane, (with ``f``) too far from that constrained
        focal length, or (with ``drop_points``: the points the refined distortion cannot project any more are
        dropped) fewer than 90 % of the points left."""
        import pycolmap

        refined = pycolmap.Reconstruction(rec)
        cam = next(iter(refined.cameras.values()))
        cam.model = model
        cam.params = start
        try:
            self._refine_camera(refined, self.refine_principal_point if refine_principal_point is None
                                else refine_principal_point)
            error = refined.compute_mean_reprojection_error()
            if drop_points:
                pycolmap.ObservationManager(refined).filter_all_points3D(4.0, 1.5)
        except Exception as exc:  # noqa: BLE001 - pycolmap raises plain runtime errors
            log.warning("colmap: refining the %s camera failed (%s)", model, exc)
            return None
        kept = refined.num_points3D() / max(rec.num_points3D(), 1)
        after = refined.compute_mean_reprojection_error()
        params = [float(v) for v in next(iter(refined.cameras.values())).params]
        width, height = int(cam.width), int(cam.height)
        why = ("" if kept >= 0.9 else f"{100 * kept:.0f} % of the points left") or \
            ("" if after <= before else f"reprojection error {before:.3f} -> {after:.3f} px") or \
            intrinsics_sane(params, width, height, model) or \
            (far_from(params, f, width, height) if f is not None else "")
        if why:
            log.info("colmap: the %s refinement of the camera is not kept (%s)", model, why)
            return None
        return refined, error

    def _refine_camera(self, rec, refine_principal_point: bool) -> None:
        """One bundle adjustment of ``rec`` in place with its camera's focal length and distortion free (and
        the principal point when asked); single-threaded when deterministic. Raises what pycolmap raises."""
        import pycolmap

        ba = pycolmap.BundleAdjustmentOptions()
        ba.refine_focal_length = ba.refine_extra_params = True
        ba.refine_principal_point = refine_principal_point
        ba.print_summary = False
        ba.ceres.solver_options.num_threads = 1 if self.deterministic else self.num_threads
        level = pycolmap.logging.minloglevel
        try:
            pycolmap.bundle_adjustment(rec, ba)
        finally:
            pycolmap.logging.minloglevel = level  # bundle_adjustment turns COLMAP's info log back on

    def _refocus(self, rec, S: int):
        """A held camera estimated on a submap that hardly turned (the focal length is observable from
        rotation, hardly from forward motion) is refined on ``rec``, a sound submap mapped with it that turns
        at least ``REFOCUS["spread_ratio"]`` times as much (and ``REFOCUS["min_spread_deg"]``): one bundle
        adjustment with one focal length and two radial terms free (principal point held). When the focal
        length moves by at least ``REFOCUS["min_change"]``, the reprojection error drops and the estimate is
        sane, ``rec`` becomes the refined reconstruction and its camera is held from now on; otherwise
        ``rec`` is returned as it is. The refined camera has fx = fy and no tangential terms (a turning car
        hardly pitches, so a separate fy is not observable: docs/frontend.md). No point filter follows, unlike
        ``_full_model``: the focal length moves by a few percent and the radial terms stay small. Submaps
        registered into the previous one (``anchored``, incremental mapper) keep the held camera."""
        import pycolmap

        spread = _view_spread(rec)
        if self._estimated is None or spread < max(REFOCUS["spread_ratio"] * self.camera.get("spread_deg", 0.0),
                                                   REFOCUS["min_spread_deg"]):
            return rec
        cam = next(iter(rec.cameras.values()))
        if cam.model.name != "OPENCV":
            return rec
        fx, fy, cx, cy, k1, k2 = [float(v) for v in cam.params][:6]
        trial = pycolmap.Reconstruction(rec)
        tcam = next(iter(trial.cameras.values()))
        tcam.model = "RADIAL"
        tcam.params = [0.5 * (fx + fy), cx, cy, k1, k2]
        try:
            self._refine_camera(trial, refine_principal_point=False)
        except Exception as exc:  # noqa: BLE001 - pycolmap raises plain runtime errors
            log.warning("colmap: refining the held camera on keyframes %d..%d failed (%s)", *self._span, exc)
            return rec
        f, _, _, r1, r2 = [float(v) for v in next(iter(trial.cameras.values())).params]
        params = [f, f, cx, cy, r1, r2, 0.0, 0.0]
        held = 0.5 * (fx + fy)
        error, before = trial.compute_mean_reprojection_error(), rec.compute_mean_reprojection_error()
        why = intrinsics_sane(params, int(cam.width), int(cam.height))
        if why or abs(f / held - 1.0) < REFOCUS["min_change"] or not error < before:
            log.info("colmap: the held camera refined on keyframes %d..%d (turning %.0f deg): f %.1f -> %.1f px, "
                     "reprojection error %.3f -> %.3f px: not adopted%s", *self._span, spread, held, f, before, error,
                     f" ({why})" if why else "")
            return rec
        tcam = next(iter(trial.cameras.values()))
        tcam.model = "OPENCV"
        tcam.params = params
        self._adopt_camera(trial, S, f"refined on keyframes {self._span[0]}..{self._span[1]} (turning "
                                     f"{spread:.0f} deg, the previous estimate's submap "
                                     f"{self.camera.get('spread_deg', 0.0):.0f} deg)")
        return trial

    def _check(self, rec, db: Path) -> list[PairCheck]:
        """The consecutive keyframe pairs whose verified matches ``rec`` contradicts (colmap_checks.py)."""
        return inconsistent(check_pairs(rec, db, seed=self.seed, config=self.fold_check), self.fold_check) \
            if self.fold_check is not None else []

    def _map_anchored(self, db: Path, images: Path, work: Path, names: list[str]):
        """Register the submap into an anchor made of the keyframes it shares with the previous
        submap's reconstruction (their poses held fixed, with the 3-D points they observe), so that it
        comes out in the previous submap's frame and scale. None when there is no usable anchor."""
        import pycolmap

        if self._previous is None:
            return None
        prev = self._previous
        shared = [n for n in names if n in self._previous_names and
                  (im := prev.find_image_with_name(n)) is not None and im.has_pose]
        if len(shared) < 2:
            return None
        database = pycolmap.Database.open(db)
        try:
            ids = {im.name: im.image_id for im in database.read_all_images()}
            camera_id = database.read_all_cameras()[0].camera_id
        finally:
            database.close()
        cam = next(iter(prev.cameras.values()))
        anchor = pycolmap.Reconstruction()
        anchor.add_camera_with_trivial_rig(pycolmap.Camera(model=cam.model, width=cam.width, height=cam.height,
                                                           params=cam.params, camera_id=camera_id))
        new_id = {}
        for n in shared:
            im = prev.find_image_with_name(n)
            keypoints = np.array([p.xy for p in im.points2D], dtype=np.float64).reshape(-1, 2)
            anchor.add_image_with_trivial_frame(
                pycolmap.Image(name=n, keypoints=keypoints, camera_id=camera_id, image_id=ids[n]), im.cam_from_world())
            new_id[im.image_id] = ids[n]
        for point in prev.points3D.values():
            elements = [e for e in point.track.elements if e.image_id in new_id]
            if len(elements) >= 2:
                track = pycolmap.Track()
                for e in elements:
                    track.add_element(new_id[e.image_id], e.point2D_idx)
                anchor.add_point3D(point.xyz, track, point.color)
        if anchor.num_points3D() < 20:
            return None
        self._anchor_names = shared
        (work / "anchor").mkdir()
        anchor.write(work / "anchor")
        opts = self._options(ATTEMPTS[0][0], 0, 0, refine=False)
        opts.fix_existing_frames = self.fix_anchor
        out = work / "sparse_anchored"
        out.mkdir()
        try:
            recs = pycolmap.incremental_mapping(db, images, out, options=opts, input_path=work / "anchor")
        except Exception as exc:  # noqa: BLE001 - pycolmap raises plain runtime errors
            log.warning("colmap anchored mapping failed: %s", exc)
            return None
        return max(recs.values(), key=lambda r: r.num_reg_images()) if recs else None

    def _options(self, angle: float, seed_offset: int, attempt: int, refine: bool):
        import pycolmap

        opts = pycolmap.IncrementalPipelineOptions()
        opts.num_threads = 1 if self.deterministic else self.num_threads
        opts.random_seed = self.seed + seed_offset
        opts.multiple_models = False
        opts.mapper.init_min_tri_angle = angle
        if attempt:
            opts.mapper.init_min_num_inliers = 50
            opts.min_model_size = 3
        if not refine:
            opts.ba_refine_focal_length = False
            opts.ba_refine_principal_point = False
            opts.ba_refine_extra_params = False
        else:
            opts.ba_refine_principal_point = self.refine_principal_point and not self._staged
        return opts

    def _global_options(self, seed_offset: int, refine: bool):
        import pycolmap

        opts = pycolmap.GlobalPipelineOptions()
        threads = 1 if self.deterministic else self.num_threads
        seed = self.seed + seed_offset
        opts.num_threads = opts.mapper.num_threads = threads
        opts.random_seed = opts.mapper.random_seed = seed
        opts.mapper.rotation_averaging.random_seed = opts.mapper.global_positioning.random_seed = seed
        opts.mapper.global_positioning.use_gpu = False
        opts.multiple_models = False
        ba = opts.mapper.bundle_adjustment
        ba.refine_focal_length = ba.refine_extra_params = refine
        ba.refine_principal_point = refine and self.refine_principal_point and not self._staged
        return opts

    def _map(self, db: Path, images: Path, out: Path, angle: float | None, seed_offset: int, attempt: int,
             refine: bool):
        """One mapping attempt (incremental; global when ``angle`` is None); the reconstruction with most
        registered images, or None."""
        import pycolmap

        out.mkdir()
        try:
            if angle is None:
                recs = pycolmap.global_mapping(db, images, out, self._global_options(seed_offset, refine))
            else:
                recs = pycolmap.incremental_mapping(db, images, out,
                                                    options=self._options(angle, seed_offset, attempt, refine))
        except Exception as exc:  # noqa: BLE001 - pycolmap raises plain runtime errors
            log.warning("colmap mapping attempt %d failed: %s", attempt, exc)
            return None
        return max(recs.values(), key=lambda r: r.num_reg_images()) if recs else None

    def _adopt_camera(self, rec, S: int, source: str) -> None:
        """Hold ``rec``'s estimated camera for the rest of the sequence when it is sensible."""
        cam = next(iter(rec.cameras.values()))
        params = [float(v) for v in cam.params]
        why = intrinsics_sane(params, int(cam.width), int(cam.height), cam.model.name)
        history = self.camera.get("history", [])
        spread = round(_view_spread(rec), 1)
        history.append({"keyframes": list(self._span), "model": cam.model.name, "params": params,
                        "registered": rec.num_reg_images(),
                        "frames": S, "spread_deg": spread, "adopted": not why, "reason": why or source})
        if why:
            log.warning("colmap: estimated intrinsics not adopted: %s", why)
            self.camera = {**self.camera, "history": history}
            return
        self._estimated = ((int(cam.width), int(cam.height)), params, cam.model.name)
        self.camera = {"model": cam.model.name, "params": params, "width": int(cam.width), "height": int(cam.height),
                       "source": source, "spread_deg": spread, "history": history}
        log.info("colmap: %s camera %s: %s", cam.model.name, source, " ".join(f"{v:.4g}" for v in params))

    def _keep_features(self, db: Path, rec) -> Path:
        """A copy of the submap's feature database with the reconstruction's final camera in it (an estimated
        camera is refined by bundle adjustment; the database still holds its starting values)."""
        import pycolmap

        out = self._features / f"{self._count:06d}.db"
        shutil.copyfile(db, out)
        database = pycolmap.Database.open(out)
        try:
            for cam in rec.cameras.values():
                database.update_camera(cam)
        finally:
            database.close()
        return out

    def _link_to_previous(self, rec, T_ref_world: np.ndarray, pred: SubmapPrediction) -> None:
        """The Sim(3) link to the previous submap from a joint bundle adjustment (``colmap_joint``), in the two
        predictions' frames, as ``pred.info["joint_link"]``: {"prev_frames", "T_prev_curr", "residual" (the
        cameras' placement residual, previous submap units), "relative_residual" (that over the cameras'
        spread)}; nothing when the two cannot be joined, or with ``link`` "auto" when the cameras move ahead."""
        if self.link == "auto":
            ahead = forward_motion([self._previous, rec], [self._previous_names, None])
            if not ahead < FORWARD_MOTION_COS:
                log.debug("colmap: forward motion (median |cos| %.2f): linked by the shared keyframes", ahead)
                return
        found = joint_link([(self._previous, self._previous_names), (rec, None)],
                           threads=1 if self.deterministic else self.num_threads)
        if found is None:
            return
        T, residual, relative = found
        T_prev_curr = self._previous_ref @ T @ se3_inverse(T_ref_world)
        pred.info["joint_link"] = {"prev_frames": sorted(int(n[:-4]) for n in self._previous_names),
                                   "T_prev_curr": T_prev_curr.tolist(), "residual": residual,
                                   "relative_residual": relative}

    # -- conversion -----------------------------------------------------------------------------
    def predict(self, frames: Sequence[Frame]) -> SubmapPrediction:
        S = len(frames)
        work = Path(tempfile.mkdtemp(prefix="vggt_slam_colmap_"))
        self._count += 1
        self._span = (int(frames[0].index), int(frames[-1].index))
        try:
            rec, names = self._reconstruct(work, frames) if S >= 2 else (None, [])
            pred = self._to_prediction(rec, names, frames)
            if rec is not None and pred.valid.sum() >= 2:
                features = str(self._keep_features(work / "database.db", rec)) if self._features is not None else None
                if features is not None:
                    pred.info["features"] = features
                T_ref_world = np.vstack([rec.find_image_with_name(names[int(np.argmax(pred.valid))])
                                         .cam_from_world().matrix(), [0.0, 0.0, 0.0, 1.0]])
                if self.link != "shared" and self._previous is not None and not self._anchor_names:
                    self._link_to_previous(rec, T_ref_world, pred)
                self._pending.append((tuple(int(f.index) for f in frames), rec, features, T_ref_world))
            return pred
        finally:
            if self.keep_workdir is not None:
                shutil.copytree(work, self.keep_workdir / f"submap_{self._count:05d}", dirs_exist_ok=True)
            shutil.rmtree(work, ignore_errors=True)

    def _to_prediction(self, rec, names: list[str], frames: Sequence[Frame]) -> SubmapPrediction:
        S = len(frames)
        h, w = frames[0].height, frames[0].width
        indices = np.array([f.index for f in frames])
        empty_pts = [np.zeros((0, 3), np.float32) for _ in range(S)]
        empty = dict(points=empty_pts, conf=[np.zeros(0, np.float32) for _ in range(S)],
                     pixels=[np.zeros((0, 2), np.float32) for _ in range(S)],
                     keys=[np.zeros(0, np.int64) for _ in range(S)])
        eye = np.repeat(np.eye(3)[None], S, 0)
        if rec is None or rec.num_reg_images() == 0:
            log.warning("colmap: submap with frames %d..%d could not be reconstructed; all frames invalid",
                        indices[0], indices[-1])
            return SubmapPrediction(indices, np.repeat(np.eye(4)[None], S, 0), eye.copy(), (h, w), eye,
                                    valid=np.zeros(S, bool), dense=False, info={"registered": 0}, **empty)
        by_name = {img.name: img for img in rec.images.values() if img.has_pose}
        if self._cut:  # the keyframes from the first contradicted pair on are not trusted (split off)
            by_name = {n: img for n, img in by_name.items() if n < self._cut}
        if self.calibrated and frames[0].intrinsics is not None:
            if not self.camera:
                cam = next(iter(rec.cameras.values()))
                self.camera = {"model": "OPENCV", "params": [float(v) for v in cam.params], "source": "given",
                               "width": int(cam.width), "height": int(cam.height)}
        elif rec.num_reg_images() >= max(3, S // 2) and not self._folds and \
                not (self.freeze_estimated and self._estimated is not None):
            self._adopt_camera(rec, S, f"estimated on keyframes {self._span[0]}..{self._span[1]}")
        T_cam_world = np.full((S, 4, 4), np.nan)
        Ks = np.zeros((S, 3, 3))
        valid = np.zeros(S, bool)
        for i, name in enumerate(names):
            img = by_name.get(name)
            if img is None:
                continue
            T_cam_world[i] = np.vstack([img.cam_from_world().matrix(), [0, 0, 0, 1]])
            Ks[i] = rec.cameras[img.camera_id].calibration_matrix()
            valid[i] = True
        ref = int(np.argmax(valid))  # frame 0 when registered
        if not valid[0]:
            log.warning("colmap: the submap's first frame %d is not registered; its pose is a guess", indices[0])
        T_world_ref = se3_inverse(T_cam_world[ref])
        T_cam_submap = T_cam_world @ T_world_ref
        for i in range(S):  # unregistered frames hold the nearest registered neighbour's pose
            if not valid[i]:
                j = int(np.argmin(np.where(valid, np.abs(np.arange(S) - i), S + 1)))
                T_cam_submap[i], Ks[i] = T_cam_submap[j], Ks[j]
        T_submap_world = se3_inverse(T_world_ref)
        pts, conf, pix, keys = [], [], [], []
        for i, name in enumerate(names):
            img = by_name.get(name)
            if img is None:
                pts.append(empty["points"][i])
                conf.append(empty["conf"][i])
                pix.append(empty["pixels"][i])
                keys.append(empty["keys"][i])
                continue
            idx = np.asarray(img.get_observation_point2D_idxs(), dtype=np.int64)
            p, c, x = [], [], []
            for k in idx:
                p2 = img.point2D(int(k))
                p3 = rec.point3D(p2.point3D_id)
                p.append(p3.xyz)
                c.append(p3.track.length() / (1.0 + p3.error))
                x.append(p2.xy)
            P = np.array(p, dtype=np.float64).reshape(-1, 3)
            pts.append((P @ T_submap_world[:3, :3].T + T_submap_world[:3, 3]).astype(np.float32))
            conf.append(np.array(c, np.float32))
            pix.append(np.array(x, np.float32).reshape(-1, 2))
            keys.append(idx)
        registered = int(valid.sum())
        if registered < S:
            log.warning("colmap: %d of %d frames registered in submap %d..%d", registered, S, indices[0], indices[-1])
        anchor = [int(n[:-4]) for n in self._anchor_names]
        return SubmapPrediction(indices, T_cam_submap, Ks, (h, w), eye, pts, conf, pix, keys, valid, dense=False,
                                info={"registered": registered, "points3D": rec.num_points3D(),
                                      "mean_reprojection_error": rec.compute_mean_reprojection_error(),
                                      **({"anchor_frames": anchor} if anchor else {}),
                                      **({"folded_attempts": self._folded_attempts} if self._folded_attempts else {}),
                                      **({"folded_pairs": [_pair_record(c) for c in self._folds]}
                                         if self._folds else {})})


def from_run_config(config: RunConfig, source: FrameSource) -> Backbone:
    """The ``colmap`` backbone of a run (:data:`vggt_slam_pp.plugins.BACKBONES`)."""
    b = config.backbone
    return ColmapBackbone(calibrated=config.calibrated, seed=b.seed, matcher=b.colmap_matcher,
                          deterministic=b.deterministic, keep_features=b.image_features and config.backend,
                          mapper=b.colmap_mapper, link=b.colmap_link)
