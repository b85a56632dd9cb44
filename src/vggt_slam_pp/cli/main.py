"""``vggt-slam-pp``: the command-line entry point.

Only this module prints and draws progress bars; the library logs. Any :class:`VggtSlamError` becomes a
one-line ``error: ...`` message on stderr and exit code 2.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from pathlib import Path

import numpy as np

from vggt_slam_pp import __version__
from vggt_slam_pp.configs import PRESETS
from vggt_slam_pp.errors import VggtSlamError
from vggt_slam_pp.plugins import BACKBONES, ENCODERS

log = logging.getLogger("vggt_slam_pp")


def _print_json(obj: dict) -> None:
    print(json.dumps(obj, indent=2, default=lambda o: o.tolist() if isinstance(o, np.ndarray) else str(o)))


def _progress(total: int, desc: str, disable: bool = False):
    from tqdm import tqdm

    bar = tqdm(total=total, desc=desc, unit="frame", disable=disable, file=sys.stderr)

    def update(done: int, _total: int) -> None:
        bar.update(done - bar.n)
        if done >= _total:
            bar.close()

    return update


# ------------------------------------------------------------------ eval
def cmd_eval(args: argparse.Namespace) -> int:
    from vggt_slam_pp.eval import compute_ate, compute_rpe
    from vggt_slam_pp.io.trajectory import read_trajectory

    gt = read_trajectory(args.gt, args.gt_format or args.format, args.gt_times)
    est = read_trajectory(args.est, args.est_format or args.format, args.est_times)
    ate = compute_ate(gt, est, args.align, args.max_diff, args.offset)
    result = ate.summary()
    if ate.n_matched > args.rpe_delta:
        result.update(compute_rpe(gt, est, args.rpe_delta, args.align, args.max_diff, args.offset).summary())
    result.update(gt=str(args.gt), est=str(args.est), gt_poses=len(gt), est_poses=len(est))
    if args.json:
        _print_json(result)
    else:
        print(f"matched {ate.n_matched} of {len(est)} estimated poses (align {args.align}, scale {ate.scale:.4f})")
        print(f"ATE  rmse {ate.rmse:.4f}  mean {ate.mean:.4f}  median {ate.median:.4f}  max {ate.max:.4f}")
        if "rpe_trans_rmse" in result:
            print(f"RPE  trans rmse {result['rpe_trans_rmse']:.4f}  rot rmse {result['rpe_rot_rmse_deg']:.4f} deg "
                  f"(delta {args.rpe_delta} frames)")
    return 0


# ------------------------------------------------------------------ info
def cmd_info(args: argparse.Namespace) -> int:
    from vggt_slam_pp.io import open_source

    source = open_source(args.input, args.layout, ground_truth=args.gt, fps=args.fps)
    info = source.info()
    if args.json:
        _print_json(info)
    else:
        print(f"{info['path']}: {info['layout']}, {info['frames']} frames, {info['width']}x{info['height']}, "
              f"{info['duration_s']:.2f} s")
        gt = f"{info['frames_with_ground_truth']} frames matched" if info["ground_truth"] else "no"
        print(f"  depth: {'yes' if info['has_depth'] else 'no'}; intrinsics: "
              f"{'yes' if info['intrinsics'] else 'no'}; ground truth: {gt}")
    return 0


# ------------------------------------------------------------------ synth
def cmd_synth(args: argparse.Namespace) -> int:
    from vggt_slam_pp.synthetic import make_scene, write_sequence

    scene = make_scene(args.scene, trajectory_file=args.trajectory, frames=args.frames, seed=args.seed,
                       width=args.width, height=args.height, style=args.style)
    summary = write_sequence(scene, args.out, depth_scale=args.depth_scale, aperiodic=args.texture == "aperiodic",
                             progress=_progress(len(scene.trajectory), "render", args.json))
    if args.json:
        _print_json(summary)
    else:
        print(f"wrote {summary['frames']} frames ({summary['width']}x{summary['height']}, {summary['solids']} solids) "
              f"to {summary['out']} in {summary['seconds_total']:.1f} s ({summary['seconds_per_frame']:.3f} s/frame)")
    return 0


# ------------------------------------------------------------------ demo
def cmd_demo(args: argparse.Namespace) -> int:
    import dataclasses

    from vggt_slam_pp.io import open_source
    from vggt_slam_pp.pipeline import RunConfig, run
    from vggt_slam_pp.synthetic import make_scene, write_sequence

    out = Path(args.out)
    seq_dir = out / "sequence"
    if not (seq_dir / "groundtruth.txt").is_file():
        scene = make_scene("loop", frames=args.frames, seed=args.seed, width=args.width, height=args.height)
        write_sequence(scene, seq_dir, progress=_progress(len(scene.trajectory), "render"))
    source = open_source(seq_dir)
    config = RunConfig.preset("synthetic")
    config = dataclasses.replace(config, backbone=dataclasses.replace(config.backbone, seed=args.seed, noise=args.noise))
    print(f"synthetic block loop: {len(source)} frames -> {seq_dir}; running VGGT-SLAM++ (simulated backbone, "
          "hog encoder, offline)")
    report = run(source, config, out / "run", progress=_progress(len(source), "frames"),
                 input_record={**_INPUT_FLAGS, "input": str(seq_dir.resolve())})  # the viewer's thumbnails, --resume
    _print_summary(report, out / "run")
    return 0


# ------------------------------------------------------------------ weights
def cmd_weights(args: argparse.Namespace) -> int:
    from vggt_slam_pp.models import weights as W

    if args.action == "import":
        if len(args.targets) != 1:
            raise VggtSlamError("weights import takes exactly one PATH (and --name)")
        target = W.import_weights(args.targets[0], args.name)
        print(f"imported {args.targets[0]} as {args.name}: {target} ({target.stat().st_size / 1e9:.2f} GB)")
        return 0
    if args.action == "fetch":
        for name in args.targets or ["vggt-1b"]:
            path = W.fetch_weights(name)
            print(f"{name}: {path}")
        return 0
    if args.targets:
        raise VggtSlamError("weights list takes no arguments")
    cached = W.cached_weights()
    if args.json:
        _print_json({"cache_dir": str(W.cache_dir()), "weights": [
            {"name": c.name, "path": str(c.path), "bytes": c.size_bytes, "where": c.where} for c in cached]})
        return 0
    print(f"our cache: {W.cache_dir()}")
    if not cached:
        print("no weights cached. Fetch with `vggt-slam-pp weights fetch vggt-1b dinov2_vitb14`, or import a "
              "local file with `vggt-slam-pp weights import PATH --name NAME`.")
    for c in cached:
        print(f"{c.name:22s} {c.size_bytes / 1e9:7.2f} GB  {c.where:11s} {c.path}")
    print(f"known names: {', '.join(W.known_names())}")
    return 0


# ------------------------------------------------------------------ run
# run flags that set a configuration field: flag's dest -> (field path in RunConfig, conversion). Unset flags
# (None) leave the preset's or the --config file's value.
_RUN_FLAGS = {
    "backbone": ("backbone.name", None), "weights": ("backbone.weights", None), "device": ("backbone.device", None),
    "replay": ("backbone.replay_dir", str), "noise": ("backbone.noise", None), "seed": ("backbone.seed", None),
    "matcher": ("backbone.colmap_matcher", None), "mapper": ("backbone.colmap_mapper", None),
    "link": ("backbone.colmap_link", None),
    "deterministic": ("backbone.deterministic", None),
    "image_loops": ("backbone.image_features", None),
    "tau": ("frontend.keyframes.tau_disparity", None), "submap_size": ("frontend.submap_size", None),
    "overlap": ("frontend.overlap", None), "calibrated": ("calibrated", None),
    "no_save_predictions": ("save_predictions", lambda v: not v), "no_backend": ("backend", lambda v: not v),
    "encoder": ("backend_config.encoder", None), "encoder_weights": ("backend_config.encoder_weights", None),
    "map_voxel": ("outputs.map_voxel", None), "no_report": ("outputs.html_report", lambda v: not v),
}


def run_config_from_args(args: argparse.Namespace):
    """The run's configuration: the preset (default ``vggt``) or the ``--config`` file, then every flag given."""
    import dataclasses

    from vggt_slam_pp.pipeline import RunConfig

    base = RunConfig.load(args.config) if args.config else RunConfig.preset(args.preset or "vggt")
    data = dataclasses.asdict(base)
    for dest, (path, convert) in _RUN_FLAGS.items():
        value = getattr(args, dest)
        if value is None:
            continue
        *parents, leaf = path.split(".")
        node = data
        for key in parents:
            node = node[key]
        node[leaf] = convert(value) if convert else value
    return RunConfig.from_dict(data)


# run flags that choose the input (and their defaults): input.json keeps them for --resume
_INPUT_FLAGS = {"input": None, "layout": "auto", "gt": None, "stride": 1, "max_frames": None, "map": None,
                "localize_only": False}


def _open_input(given: dict):
    from vggt_slam_pp.io import open_source
    from vggt_slam_pp.io.frames import FrameSubset

    source = open_source(given["input"], layout=given["layout"], ground_truth=given["gt"], stride=given["stride"])
    return FrameSubset.every(source, 1, given["max_frames"]) if given["max_frames"] else source


def cmd_run(args: argparse.Namespace) -> int:
    from vggt_slam_pp.errors import InputError
    from vggt_slam_pp.pipeline import RunConfig, run

    if args.localize_only and not args.map:
        raise InputError("--localize-only needs --map DIR")
    if args.resume:
        given = [f"--{dest.replace('_', '-')}" for dest in (*_RUN_FLAGS, *_INPUT_FLAGS, "out", "config", "preset")
                 if getattr(args, dest) not in (None, _INPUT_FLAGS.get(dest))]
        if given:
            raise InputError(f"--resume takes the input and the configuration from {args.resume}; drop "
                             f"{', '.join(given)}")
        folder = args.resume
        try:
            given_input = json.loads((folder / "input.json").read_text())
        except (OSError, json.JSONDecodeError) as exc:
            raise InputError(f"cannot resume {folder}: no readable input.json ({exc})") from None
        config, out = RunConfig.load(folder / "config.json"), folder
    else:
        if args.input is None or args.out is None:
            raise InputError("run needs --input and --out (or --resume DIR)")
        given_input = {dest: getattr(args, dest) for dest in _INPUT_FLAGS}
        given_input.update(input=str(args.input.resolve()), gt=str(args.gt.resolve()) if args.gt else None,
                           map=str(args.map.resolve()) if args.map else None)
        config, out = run_config_from_args(args), args.out
    source = _open_input(given_input)
    viewer = None
    if args.viewer:
        from vggt_slam_pp.viz.live import LiveViewer

        viewer = LiveViewer(port=args.port)
        print(f"live viewer: {viewer.url}", file=sys.stderr)
    try:
        report = run(source, config, out, progress=_progress(len(source), "frames", disable=args.quiet),
                     resume=bool(args.resume), prior_map=given_input.get("map"),
                     localize_only=bool(given_input.get("localize_only")),
                     input_record=None if args.resume else given_input, viewer=viewer)
        _print_summary(report, out)
        if viewer is not None:
            viewer.close(keep_serving=True)
            print(f"the live viewer still serves {viewer.url} (Ctrl-C to stop; `vggt-slam-pp view {out}` shows "
                  "the finished run with its DEM and loop candidates)")
            try:
                while viewer.alive():
                    time.sleep(0.5)
            except KeyboardInterrupt:  # the way to stop it: the run itself has finished
                print("viewer stopped", file=sys.stderr)
    finally:
        if viewer is not None:
            viewer.close()
    return 0


def _metres(value: float | None) -> str:
    return "-" if value is None else f"{value:.3f} m"


def _fraction(value: float | None) -> str:
    return "-" if value is None else f"{value:.3f}"


def _print_summary(report: dict, out) -> None:
    msg = (f"{report['frames_processed']} frames -> {report['keyframes']} keyframes, {report['submaps']} submaps "
           f"in {report['seconds_total']:.1f} s ({report['fps']:.2f} frames/s)")
    print(msg)
    if "placed_fraction" in report:
        rest = report["submaps"] - report["placed_submaps"]
        print(f"map: {report['map_submaps']} submaps; {report['placed_submaps']} of this recording's {report['submaps']} "
              f"submaps placed in it ({100 * report['placed_fraction']:.0f} %)"
              + (f"; {rest} not placed keep their own frame" if rest else ""))
    if report.get("resumed_backbone_calls"):
        print(f"resumed: {report['resumed_backbone_calls']} backbone calls read from predictions/")
    edges = report.get("edges", [])
    degraded = [e for e in edges if e["degraded"]]
    recovered = [e for e in edges if e.get("cause") and not e["degraded"]]
    if degraded:
        print(f"WARNING: {len(degraded)} of {len(edges)} odometry edges degraded (given a large uncertainty; "
              f"see report.json): " + "; ".join(f"{e['prev']}->{e['curr']} {e['cause']}" for e in degraded[:5]))
    elif edges:
        print(f"odometry: {len(edges)} edges, none degraded" +
              (f" ({len(recovered)} recovered by a bridge)" if recovered else ""))
    if report.get("camera", {}).get("source", "given") != "given":
        cam = report["camera"]
        from vggt_slam_pp.frontend.backbones.colmap_camera import parameter_names

        model = cam.get("model", "OPENCV")
        print(f"camera ({cam['source']}): {model} {parameter_names(model)} = "
              + " ".join(f"{v:.4g}" for v in cam["params"]))
    if "loops_accepted" in report:
        print(f"loops: {report['loops_accepted']} accepted, {report['loops_rejected']} candidates rejected (of which "
              f"{report.get('loops_pending', 0)} verified without a consistent second loop, "
              f"{report.get('loops_dropped_by_graph', 0)} dropped by the pose graph); "
              f"back-end {report['backend_s_per_submap'] * 1000:.0f} ms per submap")
    if "ate_rmse_odometry" in report:
        line = f"ATE rmse (Sim(3)-aligned, keyframes): odometry {report['ate_rmse_odometry']:.4f}"
        if "ate_rmse" in report:
            red = 100 * report.get("ate_reduction", 0.0)
            if not np.isfinite(red) or abs(red) < 0.05:
                change = "unchanged"
            elif red > 0:
                change = f"{red:.1f} % lower"
            else:
                change = f"{-red:.1f} % higher" + (": the loops did not help" if report.get("loops_accepted") else "")
            line += f", corrected {report['ate_rmse']:.4f} ({change})"
        print(line)
    files = "keyframes_odometry.txt/.kitti, frames_odometry.txt/.kitti, frames.csv, report.json, config.json"
    if "loops_accepted" in report:
        files = ("keyframes.txt/.kitti, frames.txt/.kitti (corrected), " + files +
                 ", graph.json, map.ply, dem/, trajectory.png")
    has_report = (Path(out) / "report.html").is_file()
    if has_report:
        files += ", report.html"
    print(f"outputs: {out}/ ({files})")
    print("see it: " + (f"open {out}/report.html, or " if has_report else "") +
          f"`vggt-slam-pp view {out}` for the 3-D viewer")


# ------------------------------------------------------------------ evaluate
def cmd_evaluate(args: argparse.Namespace) -> int:
    from vggt_slam_pp.suite import load_suite, run_suite, write_plots, write_tables

    suite = load_suite(args.suite)  # every check before anything runs
    out = args.out or Path("runs") / f"suite_{suite.name}"

    def progress(r: dict, done: int, total: int) -> None:
        what = f"ATE {r['ate']:.4f}" if r.get("error") is None and r.get("ate") is not None else \
            (f"FAILED: {r['error']}" if r.get("error") else "no ATE (no ground truth)")
        print(f"[{done}/{total}] {r['config']} {r['dataset']}/{r['sequence']} seed {r['seed']}: {what}", file=sys.stderr)

    results = run_suite(suite, out, runs=args.runs, jobs=args.jobs, ray=args.ray, progress=progress)
    paths = write_tables(results, out)
    write_plots(results, out)
    print(paths["md"].read_text(), end="")
    failed = sum(r.get("error") is not None for r in results)
    print(f"{len(results)} runs ({failed} failed); tables {out}/table.{{md,csv,tex}}, plots {out}/plots/")
    return 0


# ------------------------------------------------------------------ report / view
def cmd_report(args: argparse.Namespace) -> int:
    from vggt_slam_pp.viz.report import write_report

    print(f"report: {write_report(args.run_dir, args.out)}")
    return 0


def cmd_view(args: argparse.Namespace) -> int:
    from vggt_slam_pp.viz.viewer import serve

    viewer = serve(args.run_dir, host=args.host, port=args.port, max_points=args.max_points)
    print(f"viewer: http://localhost:{viewer.port}/ (Ctrl-C to stop)")
    try:
        viewer.wait()
    except KeyboardInterrupt:  # the way to stop it
        print("viewer stopped", file=sys.stderr)
    finally:
        viewer.stop()
    return 0


# ------------------------------------------------------------------ bench
def cmd_bench(args: argparse.Namespace) -> int:
    from vggt_slam_pp import benchmarks

    if args.suite == "dem":
        result = benchmarks.bench_dem(n_points=args.points)
        summary = (f"rasterised {result['points']:,} points (softmax) in {result['seconds']:.3f} s: "
                   f"{result['points_per_s'] / 1e6:.1f} M points/s, {result['ratio_to_count_baseline']:.2f}x the "
                   f"index+bincount baseline (target <= 3)")
    elif args.suite == "retrieval":
        result = benchmarks.bench_retrieval()
        summary = (f"HNSW recall@10 at 100k tiles {result['recall_at_10']:.3f} (target >= 0.95); latency "
                   f"{result['latency_ms_10k']:.3f} ms (10k) -> {result['latency_ms_100k']:.3f} ms (100k), ratio "
                   f"{result['latency_ratio_100k_10k']:.2f} (target <= 3)")
    elif args.suite == "frontend":
        data = args.data or _default_data()
        result = benchmarks.bench_frontend(data, workdir=str(args.workdir or "runs/bench_frontend"), runs=args.runs,
                                           sequences=args.sequence or None, deterministic=args.deterministic,
                                           link=args.link, progress=lambda name: print(f"{name} ...", file=sys.stderr))
        summary = _frontend_table(result)
    elif args.suite == "loops" and args.backbone == "colmap":
        result = benchmarks.bench_loops_colmap(workdir=str(args.workdir or "runs/bench_loops_colmap"), seed=args.seed,
                                               progress=lambda name: print(f"scenario {name} ...", file=sys.stderr))
        summary = _loops_table(result)
    elif args.suite == "loops":
        result = benchmarks.bench_loops(trajectories=args.trajectory, frames=args.frames,
                                        workdir=str(args.workdir or "runs/bench_loops"),
                                        fps_repeats=args.fps_repeats, seed=args.seed, noise=args.noise,
                                        progress=lambda name: print(f"scenario {name} ...", file=sys.stderr))
        summary = _loops_table(result)
    elif args.suite == "registration":
        result = benchmarks.bench_registration(frames=args.frames, seed=args.seed, displacement=args.displacement,
                                               noise=args.noise,
                                               workdir=str(args.workdir or "runs/bench_loops"),
                                               progress=lambda name: print(f"scene {name} ...", file=sys.stderr))
        summary = _per_scene(result["scenes"], lambda r: (
            f"{r['found']} of {r['positives']} revisits registered correctly from a displaced estimate "
            f"(recall {r['recall']:.2f}), {r['false_accepted']} of {r['negatives']} other places accepted; "
            f"{r['seconds_median']:.2f} s per pair (median); outcomes {r['outcomes']}"))
    elif args.suite == "relocalization":
        rows = [benchmarks.bench_relocalization(frames=args.frames, seed=args.seed, noise=args.noise, reverse=reverse,
                                                workdir=str(args.workdir or "runs/bench_relocalization"),
                                                progress=lambda name: print(f"{name} ...", file=sys.stderr))
                for reverse in (True, False)]
        result = {"passes": rows, **{k: rows[0][k] for k in ("placed_fraction", "false_placements", "ate_map",
                                                              "ate_second_pass_map_frame")}}
        summary = "\n".join(
            f"second pass {'the other way' if r['reverse'] else 'the same way'}: {r['second_pass_submaps']} submaps, "
            f"placed {r['placed_fraction']:.2f} (target >= 0.9), false placements {r['false_placements']} (target 0), "
            f"ATE in the map's frame {_metres(r['ate_second_pass_map_frame'])} (map {_metres(r['ate_map'])}; target "
            f"<= 2x); the map's own ATE once extended {_metres(r['ate_map_extended'])}; loops between the two "
            f"passes {r['loops_across']}, off the truth by > 5 deg / 5 m {len(r['wrong_loops_across'])}" for r in rows)
    elif args.suite == "memory":
        result = benchmarks.bench_memory(submaps=args.submaps, workdir=str(args.workdir or "runs/bench_memory"),
                                         seed=args.seed, laps=args.laps)
        summary = (f"{result['submaps']} submaps ({result['frames']} frames): RSS (front-end + back-end) "
                   f"{result['rss_mb_at_50']:.0f} MiB at 50 submaps, {result['rss_mb_at_300']:.0f} MiB at 300: "
                   f"growth {100 * result['growth']:.1f} % (target < 20 %)")
        if result.get("backend_s_per_submap_first100") is not None:  # 200 submaps or more: issue 24's figures
            r = result
            summary += (f"\nback-end s per submap, submaps 100-199 / the last 100: {r['backend_s_per_submap_first100']:.3f}"
                        f" / {r['backend_s_per_submap_last100']:.3f} wall (target: last <= 1.3x first), "
                        f"{r['backend_cpu_s_per_submap_first100']:.3f} / {r['backend_cpu_s_per_submap_last100']:.3f} "
                        f"CPU; peak RSS {r['peak_rss_mb_all']:.0f} MiB (target <= 1024); submit wait "
                        f"{100 * (r['frontend_submit_wait_fraction'] or 0):.1f} % (target <= 5 %); lag "
                        f"{r['backend_max_lag_submaps']} submaps, {r['backend_queries_deferred']} queries deferred; "
                        f"ATE reduction {_fraction(r['ate_reduction'])} (target >= 0.60); false loops "
                        f"{r['false_loops']} (target 0)")
            if r.get("backend_stage_s_first100"):
                summary += "\nby stage, s per submap, 100-199 / the last 100: " + ", ".join(
                    f"{k.removesuffix('_s')} {v:.3f} / {r['backend_stage_s_last100'].get(k, 0.0):.3f}"
                    for k, v in r["backend_stage_s_first100"].items())
    else:
        result = benchmarks.bench_covisibility(frames=args.frames, seed=args.seed, noise=args.noise,
                                               workdir=str(args.workdir or "runs/bench_covisibility"))
        summary = _per_scene(result["scenes"], lambda r: (
            f"{r['submaps']} submaps, {r['revisit_queries']} revisit queries, covisibility recall "
            f"{r['covisibility_recall']} (voting alone {r['covisibility_recall_votes']}), loop candidate recall "
            f"{r['candidate_recall']}, VPR top-1 precision {r['vpr_top1_precision']}"))
        summary += (f"\nmean: covisibility recall {result['covisibility_recall']} (target >= 0.9; voting alone "
                    f"{result['covisibility_recall_votes']}), loop candidate recall {result['candidate_recall']}, "
                    f"VPR top-1 precision {result['vpr_top1_precision']} (target >= 0.8)")
    if args.json:
        _print_json(result)
    else:
        print(summary)
    return 0


def _per_scene(scenes: dict, line) -> str:
    """One line per scene: ``line(result)``, or why the scene was skipped."""
    return "\n".join(f"{name}: {r['skipped']}" if "skipped" in r else f"{name}: {line(r)}"
                     for name, r in scenes.items())


def _default_data() -> Path:
    """``../shared/data`` next to the working folder or the source checkout, if there is one."""
    here = Path(__file__).resolve().parents[3]
    for cand in (Path.cwd().parent / "shared" / "data", here.parent / "shared" / "data"):
        if cand.is_dir():
            return cand
    return Path.cwd().parent / "shared" / "data"


def _frontend_table(result: dict) -> str:
    head = (f"{'sequence':<28}{'runs':>5}{'ATE med':>9}{'worst':>8}{'std':>8}{'% path':>8}{'degraded':>9}"
            f"{'recovered':>10}{'keyframes':>10}{'reg. min':>9}{'fps':>7}{'placed':>8}{'offset':>8}{'ATE there':>10}")
    rows = [f"colmap front-end, seeds 0..{result['runs'] - 1}, no back-end; ATE: Sim(3)-aligned keyframes, metres",
            "diagnostics, not results: placed: the ATE with each submap placed where it fits the truth best (the error "
            "inside the submaps; the odometry edges add the rest); offset: the time offset (ms) added to the estimate "
            "that fits best, with the ATE there (a clock lag and an along-track error both show as an offset)", head]
    for r in result["sequences"]:
        if "skipped" in r:
            rows.append(f"{r['name']:<28}skipped: {r['skipped']}")
            continue
        offset = r.get("time_offset_s_median")
        rows.append(f"{r['name']:<28}{r['runs']:>5}{r['ate_median']:>9.4f}{r['ate_worst']:>8.4f}{r['ate_std']:>8.4f}"
                    f"{r['ate_median_pct_path']:>7.2f}%{r['degraded_edges_total']:>9}{r['recovered_edges_total']:>10}"
                    f"{r['keyframes_median']:>10.0f}{r['registered_frames_min']:>9}{r['fps']:>7.2f}"
                    f"{_or_dash(r.get('ate_submaps_placed_best_median'), '8.4f', 8)}"
                    f"{_or_dash(offset if offset is None else 1000 * offset, '+8.0f', 8)}"
                    f"{_or_dash(r.get('ate_at_time_offset_median'), '10.4f', 10)}")
    return "\n".join(rows)


def _or_dash(value: float | None, spec: str, width: int) -> str:
    """``value`` right-aligned with format ``spec`` (sign, width, precision), or a dash ``width`` wide where it
    is missing."""
    return f"{value:>{spec}}" if value is not None else f"{'-':>{width}}"


def _loops_table(result: dict) -> str:
    head = (f"{'scenario':<12}{'submaps':>8}{'ATE odo':>9}{'drift':>7}{'ATE final':>10}{'reduct.':>8}{'loops':>6}{'false':>6}"
            f"{'s/submap':>9}{'fps on':>8}{'fps off':>8}{'RSS MiB':>8}")
    colmap = result.get("backbone") == "colmap"
    rows = ["colmap backbone on rendered images (loops from images)" if colmap else
            f"simulated backbone, {result.get('noise', 'default')} noise", "drift: odometry ATE in % of the path", head]
    for name, r in result["scenarios"].items():
        if "skipped" in r:
            rows.append(f"{name:<12}skipped: {r['skipped']}")
            continue
        drift = f"{r['drift_pct_path']:.2f}%" if r.get("drift_pct_path") is not None else "-"
        fps = (f"{r['fps']:>8.1f}{'-':>8}{'-':>8}" if colmap else f"{r['frontend_fps_backend_on']:>8.1f}"
               f"{r['frontend_fps_backend_off']:>8.1f}{r['peak_rss_mb']:>8.0f}")
        rows.append(f"{name:<12}{r['submaps']:>8}{r['ate_odometry']:>9.3f}{drift:>7}{r['ate_final']:>10.3f}"
                    f"{100 * r['ate_reduction']:>7.0f}%{r['loops_accepted']:>6}{r['false_loops']:>6}"
                    f"{r['backend_s_per_submap']:>9.3f}{fps}")
    target = result.get("targets", {}).get("mean_ate_reduction", 0.5)
    rows.append(f"mean ATE reduction {100 * (result['mean_ate_reduction'] or 0):.0f} % (target >= {100 * target:.0f} %), "
                f"false loops {result['false_loops']} (target 0)" + (
                    " (a loop placing the query's cameras > 1 m from the truth; by the footprint rule of the "
                    f"simulated bench: {sum(r.get('footprint_false_loops', 0) for r in result['scenarios'].values())})"
                    if colmap else
                f", lowest fps ratio on/off {result['min_fps_ratio']:.2f} (target >= 0.9)"
                + (f"; loops > 5 deg or 5 m off the truth {result['loops_off_truth']}" if "loops_off_truth" in result
                   else "")
                + (f"; verified {result['loops_verified']}, of which off the truth {result['verified_off_truth']} "
                   "(before the consistency gate)" if "verified_off_truth" in result else "")))
    return "\n".join(rows)


NOISE_PROFILES = ("default", "realistic", "zero")


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="vggt-slam-pp", description="VGGT-SLAM++ command-line tools.")
    p.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    p.add_argument("-v", "--verbose", action="count", default=0, help="more logging (-v info, -vv debug)")
    sub = p.add_subparsers(dest="command", required=True)

    d = sub.add_parser("demo", help="generate a synthetic loop sequence and run on it, offline")
    d.add_argument("--out", default="runs/demo", help="output folder (default: runs/demo)")
    d.add_argument("--frames", type=int, default=600)
    d.add_argument("--width", type=int, default=320)
    d.add_argument("--height", type=int, default=240)
    d.add_argument("--seed", type=int, default=0)
    d.add_argument("--noise", choices=NOISE_PROFILES, default="default",
                   help="simulated backbone's noise: default, realistic (monocular drift, 1-3 %% of the path) or zero")
    d.set_defaults(func=cmd_demo)

    ev = sub.add_parser("evaluate", help="run an evaluation suite (datasets x configurations x seeds) and "
                                         "write its tables (Markdown, CSV, LaTeX) and plots")
    ev.add_argument("suite", type=Path, help="suite file (YAML; see benchmarks/suites/)")
    ev.add_argument("--out", type=Path, help="output folder (default runs/suite_NAME); finished runs in it are kept")
    ev.add_argument("--runs", type=int, help="runs per (sequence, configuration), seeds 0..N-1 (default: the suite's)")
    ev.add_argument("--jobs", type=int, default=1, help="runs at a time in local processes (default 1)")
    ev.add_argument("--ray", nargs="?", const="local", metavar="ADDRESS",
                    help="run on Ray: a local instance, or the cluster at ADDRESS (needs the ray extra)")
    ev.set_defaults(func=cmd_evaluate)

    rp = sub.add_parser("report", help="write a run's self-contained HTML report (figures, loops, timings)")
    rp.add_argument("run_dir", type=Path, help="a run's output folder")
    rp.add_argument("--out", type=Path, help="HTML file (default: RUN_DIR/report.html)")
    rp.set_defaults(func=cmd_report)

    v = sub.add_parser("view", help="3-D web viewer of a run or a map (viser; needs the viz extra)")
    v.add_argument("run_dir", type=Path, help="a run's output folder")
    v.add_argument("--port", type=int, default=8080, help="port on localhost (default 8080)")
    v.add_argument("--host", default="127.0.0.1", help="address to serve on (default 127.0.0.1)")
    v.add_argument("--max-points", type=int, default=300_000,
                   help="points shown in all, spread over the submaps (default 300000)")
    v.set_defaults(func=cmd_view)

    e = sub.add_parser("eval", help="ATE / RPE of an estimated trajectory against ground truth")
    e.add_argument("--gt", required=True, type=Path, help="ground-truth trajectory file")
    e.add_argument("--est", required=True, type=Path, help="estimated trajectory file")
    e.add_argument("--align", choices=("sim3", "se3", "none"), default="sim3")
    e.add_argument("--format", choices=("auto", "tum", "kitti", "euroc"), default="auto",
                   help="format of both files (default: detected per file)")
    e.add_argument("--gt-format", choices=("auto", "tum", "kitti", "euroc"))
    e.add_argument("--est-format", choices=("auto", "tum", "kitti", "euroc"))
    e.add_argument("--gt-times", type=Path, help="times file for a KITTI ground truth")
    e.add_argument("--est-times", type=Path, help="times file for a KITTI estimate")
    e.add_argument("--max-diff", type=float, default=0.01, help="max timestamp difference, s (default 0.01)")
    e.add_argument("--offset", type=float, default=0.0, help="time offset added to the estimate, s")
    e.add_argument("--rpe-delta", type=int, default=1, help="RPE frame step (default 1)")
    e.add_argument("--json", action="store_true", help="print a JSON object")
    e.set_defaults(func=cmd_eval)

    i = sub.add_parser("info", help="describe an input (layout, frames, resolution, time span, ground truth)")
    i.add_argument("input", type=Path)
    i.add_argument("--layout", default="auto",
                   help="auto, euroc, tum, kitti, 7scenes, vkitti2, video or images")
    i.add_argument("--gt", type=Path, help="pair the input with this ground-truth trajectory file")
    i.add_argument("--fps", type=float, default=1.0, help="frame rate of plain image folders (default 1)")
    i.add_argument("--json", action="store_true")
    i.set_defaults(func=cmd_info)

    s = sub.add_parser("synth", help="render a synthetic RGB-D sequence in TUM layout")
    g = s.add_mutually_exclusive_group(required=True)
    g.add_argument("--scene", choices=("figure8", "loop"))
    g.add_argument("--trajectory", type=Path, help="drive the camera along this TUM/KITTI/EuRoC trajectory")
    s.add_argument("--frames", type=int, default=None, help="number of frames (default 300, or all poses of a file)")
    s.add_argument("--out", required=True, type=Path)
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--width", type=int, default=640)
    s.add_argument("--height", type=int, default=480)
    s.add_argument("--style", choices=("outdoor", "indoor"), help="world style (default: from the trajectory)")
    s.add_argument("--depth-scale", type=float, default=5000.0, help="depth PNG units per metre (TUM: 5000)")
    s.add_argument("--texture", choices=("aperiodic", "periodic"), default="aperiodic",
                   help="surface texture: aperiodic (default; needed by feature matching, e.g. --backbone colmap) or "
                        "periodic (a 16 m tile, as the loop benchmarks render)")
    s.add_argument("--json", action="store_true")
    s.set_defaults(func=cmd_synth)
    r = sub.add_parser("run", help="run the system on an input and write trajectories and a report")
    r.add_argument("--input", type=Path, help="image folder, video or dataset folder")
    r.add_argument("--map", type=Path, metavar="DIR",
                   help="add this recording to the map in DIR (a finished run): it comes out in the map's frame once "
                        "loops place it, and the extended map is written to --out (DIR is never modified)")
    r.add_argument("--localize-only", action="store_true", default=False,
                   help="with --map: localise in the map without changing or extending it")
    r.add_argument("--resume", type=Path, metavar="DIR",
                   help="continue the interrupted run in DIR (its input.json and config.json) from its last "
                        "finished submap; with vggt, simulated or replay the result equals an uninterrupted run "
                        "(colmap estimates its anchor and camera again: docs/frontend.md, Resume)")
    start = r.add_mutually_exclusive_group()
    start.add_argument("--preset", choices=list(PRESETS), help="a named configuration to start from (default "
                       "vggt); flags given with it override it: " + "; ".join(
                           f"{name}: {what}" for name, (what, _) in PRESETS.items()))
    start.add_argument("--config", type=Path, help="start from this configuration file (a run's config.json); "
                                                   "flags given with it override it")
    r.add_argument("--backbone", choices=list(BACKBONES), help="default: the preset's")
    r.add_argument("--out", type=Path, help="output folder")
    r.add_argument("--calibrated", action="store_true", default=None,
                   help="use the dataset's intrinsics and distortion (undistort / known camera)")
    r.add_argument("--no-backend", action="store_true", default=None, help="front-end only (odometry)")
    r.add_argument("--encoder", choices=list(ENCODERS),
                   help="DEM encoder for covisibility (default hog: weight-free)")
    r.add_argument("--encoder-weights", default=None, help="dinov2: weights file or hub name")
    r.add_argument("--no-report", action="store_true", default=None, help="do not write report.html")
    r.add_argument("--viewer", action="store_true",
                   help="show the run live in a 3-D web viewer (viser; needs the viz extra); it keeps serving "
                        "after the run until Ctrl-C")
    r.add_argument("--port", type=int, default=8080, help="the live viewer's port (default 8080)")
    r.add_argument("--map-voxel", type=float, metavar="METRES",
                   help="map.ply: keep one point per cube of this size in each submap (default: off)")
    r.add_argument("--layout", default="auto", help="input layout (default: detected)")
    r.add_argument("--gt", type=Path, help="ground-truth trajectory file for evaluation")
    r.add_argument("--stride", type=int, default=1, help="use every N-th input frame")
    r.add_argument("--max-frames", type=int, help="stop after this many frames")
    r.add_argument("--weights", help="vggt: weights name or path (model.pt, .safetensors, folder; default vggt-1b)")
    r.add_argument("--device", help="vggt: auto (default), cpu, cuda, cuda:N")
    r.add_argument("--replay", type=Path, help="replay: folder of an earlier run (or its predictions/)")
    r.add_argument("--noise", choices=NOISE_PROFILES,
                   help="simulated: noise profile (default; realistic: monocular drift, 1-3 %% of the path; zero)")
    r.add_argument("--matcher", choices=("exhaustive", "sequential"),
                   help="colmap: match all keyframe pairs of a submap (default) or sequentially")
    r.add_argument("--mapper", choices=("global", "incremental"),
                   help="colmap: reconstruct each submap on its own with COLMAP's global mapper and link it by its "
                        "shared keyframes (default), or register it into the previous submap's shared keyframes "
                        "with the incremental mapper")
    r.add_argument("--link", choices=("auto", "shared", "joint"),
                   help="colmap, global mapper: link each submap to the previous one by their shared keyframes "
                        "(shared) or by one bundle adjustment of both, each placed by all its cameras (joint: better "
                        "on real handheld and drone sequences, worse on forward driving); auto (default): joint "
                        "unless the camera moves straight ahead")
    r.add_argument("--submap-size", type=int,
                   help="new keyframes per submap (w, default 32); photo walks and sparse keyframes: 8-16")
    r.add_argument("--overlap", type=int,
                   help="keyframes shared by consecutive submaps (default 0 = auto: 1 for vggt/simulated, "
                        "w*w/64 within 2..16 for colmap: 2 for w 8, 4 for 16, 16 for 32)")
    r.add_argument("--image-loops", action=argparse.BooleanOptionalAction, default=None,
                   help="colmap: register loop candidates from the keyframes' images (default; keeps about 10 MB "
                        "of features per submap in the run folder); --no-image-loops registers them from points")
    r.add_argument("--deterministic", action=argparse.BooleanOptionalAction, default=None,
                   help="colmap: every step on one thread, so that the same input and --seed give bit-identical "
                        "trajectories (default); --no-deterministic runs the mapper multi-threaded (~25 %% faster)")
    r.add_argument("--tau", type=float, help="keyframe LK disparity threshold, px (default 40)")
    r.add_argument("--seed", type=int, help="seed of every random choice (default 0)")
    r.add_argument("--no-save-predictions", action="store_true", default=None, help="do not write predictions/")
    r.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    r.set_defaults(func=cmd_run)

    b = sub.add_parser("bench", help="benchmarks: dem (rasterisation), retrieval (HNSW recall and latency), "
                                     "covisibility, loops (the whole system on revisits), registration (loop "
                                     "registration from a displaced estimate), memory (long run), frontend, "
                                     "relocalization (a second recording added to a map)")
    b.add_argument("suite", choices=("dem", "retrieval", "covisibility", "loops", "registration", "memory", "frontend",
                                     "relocalization"))
    b.add_argument("--runs", type=int, default=5, help="frontend: runs per sequence, seeds 0..N-1 (default 5)")
    b.add_argument("--data", type=Path, help="frontend: folder with euroc_mh05_sample/ and strecha_castle_p30_loop/ "
                                             "(default: ../shared/data when present)")
    b.add_argument("--sequence", action="append", default=[],
                   help="frontend: only this sequence (repeatable): euroc_uncalibrated, euroc_calibrated, castle, "
                        "rendered")
    b.add_argument("--deterministic", action=argparse.BooleanOptionalAction, default=True,
                   help="frontend: colmap on one thread (default; bit-identical runs per seed)")
    b.add_argument("--link", choices=("auto", "shared", "joint"), default="auto",
                   help="frontend: how consecutive colmap submaps are linked (run --link)")
    b.add_argument("--points", type=int, default=6_500_000, help="dem: number of points")
    b.add_argument("--frames", type=int, default=600, help="covisibility, loops, registration: frames per synthetic sequence")
    b.add_argument("--trajectory", type=Path, action="append", default=[],
                   help="loops: also drive a camera along this trajectory file (TUM, KITTI or EuRoC); repeatable")
    b.add_argument("--backbone", choices=("simulated", "colmap"), default="simulated",
                   help="loops: colmap runs the whole image path (images -> SfM submaps -> DEM -> loops from "
                        "images) on rendered revisits, laps of a block (slow: minutes per scenario)")
    b.add_argument("--fps-repeats", type=int, default=3,
                   help="loops: runs with and without the back-end per scenario for the fps medians")
    b.add_argument("--noise", choices=NOISE_PROFILES, default="default",
                   help="loops, covisibility, registration: the simulated backbone's noise profile (realistic: "
                        "monocular drift, 1-3 %% of the path)")
    b.add_argument("--displacement", type=float, default=1.0,
                   help="registration: the estimate is displaced within this share of the drift bounds (default 1)")
    b.add_argument("--submaps", type=int, default=320, help="memory: submaps in the long run (>= 300)")
    b.add_argument("--laps", type=int, default=0,
                   help="memory: 0 (default) the demo's block loop scaled up (two laps, the second the other way); N: "
                        "a block driven round N times the same way (revisits from the second lap on)")
    b.add_argument("--seed", type=int, default=0,
                   help="covisibility, loops, registration, memory: world and noise seed (another seed: other solids along the same "
                        "trajectories; the figures in docs/ are for seed 0 unless they say otherwise)")
    b.add_argument("--workdir", type=Path, default=None,
                   help="where rendered sequences and runs are kept (default: runs/bench_<suite>)")
    b.add_argument("--json", action="store_true")
    b.set_defaults(func=cmd_bench)

    w = sub.add_parser("weights", help="list cached weights, fetch official ones, or import a local file",
                       description="list (default): what is cached; fetch NAME...: download into the cache "
                                   "(vggt-1b, vggt-1b-commercial, dinov2_vitb14, ...); import PATH --name NAME: "
                                   "check a local checkpoint strictly and store it as safetensors")
    w.add_argument("action", nargs="?", choices=("list", "fetch", "import"), default="list")
    w.add_argument("targets", nargs="*", help="names (fetch) or one path (import)")
    w.add_argument("--name", default="vggt-1b", help="model the imported file is for (default vggt-1b)")
    w.add_argument("--json", action="store_true")
    w.set_defaults(func=cmd_weights)
    return p


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    level = logging.WARNING - 10 * min(args.verbose, 2)
    logging.basicConfig(level=level, format="%(levelname)s %(name)s: %(message)s")
    if args.verbose < 2:  # third-party retry chatter would bury our one-line errors
        logging.getLogger("huggingface_hub").setLevel(logging.ERROR)
    try:
        return int(args.func(args) or 0)
    except VggtSlamError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
