"""``vggt-slam-pp report RUN_DIR``: one self-contained HTML file for a run (figures embedded as PNG).

It holds the trajectory (top and side views: odometry, corrected, ground truth), the ATE over time and
the RPE over segment lengths, the DEM and its hillshade, the loop candidates (accepted and rejected,
with reasons, scores and guesses), the per-stage timings, the memory trace and the configuration.
Figures are drawn by matplotlib and the page by a Jinja2 template (autoescaped: reasons and paths are
text). ``run`` writes ``report.html`` at the end of every run (``OutputConfig.html_report``).
"""

from __future__ import annotations

import base64
import io
import json
import logging
from pathlib import Path

import numpy as np

from vggt_slam_pp.errors import VggtSlamError
from vggt_slam_pp.io.trajectory import atomic_write_text
from vggt_slam_pp.viz.run_folder import RunFolder, aligned_positions, load_run, motion_axes

log = logging.getLogger(__name__)

__all__ = ["write_report", "render_report", "FIGURES"]

# every figure the report can hold, in page order (a run without the back-end or ground truth has fewer)
FIGURES = ("trajectory", "ate_over_time", "rpe", "dem", "timings", "memory")

_STYLE = {"ground truth": ("k", "-"), "odometry": ("tab:red", "--"), "corrected": ("tab:blue", "-")}

_TEMPLATE = """<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>VGGT-SLAM++ run {{ name }}</title>
<style>
body { font-family: system-ui, sans-serif; margin: 2em auto; max-width: 1100px; color: #222; }
h1 { font-size: 1.5em; } h2 { font-size: 1.2em; margin-top: 2em; border-bottom: 1px solid #ccc; }
table { border-collapse: collapse; font-size: 0.85em; } td, th { border: 1px solid #ddd; padding: 2px 6px; }
th { background: #f3f3f3; } tr.accepted td { background: #eef8ee; } figure { margin: 1em 0; }
img { max-width: 100%; } pre { background: #f7f7f7; padding: 1em; overflow-x: auto; font-size: 0.8em; }
.summary td:first-child { font-weight: 600; } .scroll { max-height: 480px; overflow-y: auto; }
</style></head><body>
<h1>VGGT-SLAM++ run <code>{{ name }}</code></h1>
{% if error %}<p><strong>The run ended with an error:</strong> {{ error }}</p>{% endif %}
<table class="summary">{% for k, v in summary %}<tr><td>{{ k }}</td><td>{{ v }}</td></tr>{% endfor %}</table>
{% for fig in figures %}
<h2 id="{{ fig.id }}">{{ fig.title }}</h2>
<figure><img id="fig-{{ fig.id }}" alt="{{ fig.title }}" src="data:image/png;base64,{{ fig.png }}">
{% if fig.caption %}<figcaption>{{ fig.caption }}</figcaption>{% endif %}</figure>
{% endfor %}
<h2 id="loops">Loop candidates</h2>
{% if loops %}
<p>{{ n_accepted }} accepted, {{ loops|length - n_accepted }} rejected.</p>
<div class="scroll"><table id="loop-table"><tr><th>query</th><th>match</th><th>verdict</th><th>reason</th>
<th>source</th><th>guess</th><th>score</th><th>overlap</th><th>structure</th><th>agreement</th><th>residual</th></tr>
{% for c in loops %}<tr class="{{ 'accepted' if c.accepted else 'rejected' }}"><td>{{ c.query }}</td><td>{{ c.match }}</td>
<td>{{ 'accepted' if c.accepted else 'rejected' }}</td><td>{{ c.reason }}</td><td>{{ c.source }}</td><td>{{ c.guess }}</td>
<td>{{ c.score }}</td><td>{{ c.overlap }}</td><td>{{ c.structure_overlap }}</td><td>{{ c.agreement }}</td><td>{{ c.residual }}</td></tr>
{% endfor %}</table></div>
{% else %}<p>No loop candidates (a run without the back-end, or no revisit).</p>{% endif %}
<h2 id="configuration">Configuration</h2>
<pre>{{ config }}</pre>
</body></html>
"""


def _png(fig) -> str:
    import matplotlib.pyplot as plt

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90, bbox_inches="tight")
    plt.close(fig)
    return base64.b64encode(buf.getvalue()).decode("ascii")


def _series(run: RunFolder) -> dict[str, tuple[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray | None]]:
    """name -> aligned (timestamps, positions, truth, errors) of the odometry and corrected keyframes."""
    out = {"odometry": aligned_positions(run.odometry, run.ground_truth)}
    if run.corrected is not None:
        out["corrected"] = aligned_positions(run.corrected, run.ground_truth)
    return out


def _trajectory_figure(run: RunFolder, series: dict):
    import matplotlib.pyplot as plt

    gt = run.ground_truth
    base = gt.positions if gt is not None else series.get("corrected", series["odometry"])[1]
    mean, axes = motion_axes(base)  # most motion first, the "height" last
    fig, (top, side) = plt.subplots(1, 2, figsize=(12, 5.5), gridspec_kw={"width_ratios": [1, 1]})
    curves = ([("ground truth", gt.positions)] if gt is not None else []) + [(k, v[1]) for k, v in series.items()]
    for name, p in curves:
        colour, style = _STYLE[name]
        q = (p - mean) @ axes.T
        top.plot(q[:, 0], q[:, 1], style, color=colour, lw=1.2, label=name)
        side.plot(q[:, 0], q[:, 2], style, color=colour, lw=1.2, label=name)
    top.set_aspect("equal", adjustable="datalim")
    top.set_title("top view (plane of most motion)")
    side.set_title("side view (first axis against height)")
    for ax in (top, side):
        ax.grid(alpha=0.3)
        ax.legend(loc="best", fontsize=8)
    return fig


def _ate_figure(series: dict):
    import matplotlib.pyplot as plt

    series = {k: v for k, v in series.items() if v[3] is not None}
    if not series:  # no pose matched the ground truth
        return None
    fig, ax = plt.subplots(figsize=(12, 3.5))
    for name, (t, _, _, err) in series.items():
        colour, style = _STYLE[name]
        ax.plot(t - t[0], err, style, color=colour, lw=1.2,
                label=f"{name}: RMSE {np.sqrt(np.mean(err ** 2)):.4g}")
    ax.set_xlabel("time (s)")
    ax.set_ylabel("position error after Sim(3) alignment")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    return fig


def _rpe_figure(run: RunFolder):
    import matplotlib.pyplot as plt

    from vggt_slam_pp.eval import compute_rpe

    fig, ax = plt.subplots(figsize=(12, 3.5))
    any_curve = False
    for name, traj in (("odometry", run.odometry), ("corrected", run.corrected)):
        if traj is None:
            continue
        deltas, rmse = [], []
        for d in (1, 2, 5, 10, 20, 50):
            try:
                r = compute_rpe(run.ground_truth, traj, delta=d)
            except VggtSlamError:
                break
            deltas.append(d)
            rmse.append(r.trans_rmse)
        if deltas:
            colour, style = _STYLE[name]
            ax.plot(deltas, rmse, style, marker="o", color=colour, lw=1.2, label=name)
            any_curve = True
    if not any_curve:
        plt.close(fig)
        return None
    ax.set_xscale("log")
    ax.set_xlabel("segment (keyframes)")
    ax.set_ylabel("translational RPE (RMSE)")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8)
    return fig


def display_dem(heights: np.ndarray, mpp: float, max_px: int = 1200) -> tuple[np.ndarray, float]:
    """A DEM [H,W] reduced for a figure: the mean of each k x k block of pixels (k the least that brings the long
    side to at most ``max_px``; a block with no height stays empty), and its metres per pixel. A long run's DEM
    has tens of millions of pixels, and drawing them all took the report to about 1 GB."""
    k = int(np.ceil(max(heights.shape) / max_px))
    if k <= 1:
        return heights, mpp
    H, W = heights.shape
    padded = np.full((-(-H // k) * k, -(-W // k) * k), np.nan, np.float32)
    padded[:H, :W] = heights
    blocks = padded.reshape(padded.shape[0] // k, k, padded.shape[1] // k, k)
    valid = np.isfinite(blocks)
    count = valid.sum(axis=(1, 3))
    total = np.where(valid, blocks, np.float32(0)).sum(axis=(1, 3))
    out = np.full(count.shape, np.nan, np.float32)
    np.divide(total, count, out=out, where=count > 0)
    return out, mpp * k


def _dem_figure(run: RunFolder):
    import matplotlib.pyplot as plt

    from vggt_slam_pp.dem.images import hillshade_rgb

    heights, mpp = display_dem(run.dem["heights"], run.dem["mpp"])
    fig, (a, b) = plt.subplots(1, 2, figsize=(12, 5.5))
    extent = (0, heights.shape[1] * mpp, 0, heights.shape[0] * mpp)  # v up, as a map seen from above
    finite = heights[np.isfinite(heights)]
    lo, hi = (np.percentile(finite, [1, 99]) if len(finite) else (0.0, 1.0))
    im = a.imshow(heights, cmap="viridis", vmin=lo, vmax=hi, extent=extent, origin="lower")
    fig.colorbar(im, ax=a, shrink=0.7, label="height above the ground plane")
    a.set_title("heights")
    b.imshow(hillshade_rgb(heights, mpp=mpp), extent=extent, origin="lower")
    b.set_title("hillshade")
    for ax in (a, b):
        ax.set_xlabel("x (DEM plane)")
    return fig


def _timings_figure(report: dict):
    import matplotlib.pyplot as plt

    stages = {f"front-end {k[:-2]}": v for k, v in (report.get("timings") or {}).items()
              if isinstance(v, (int, float)) and k.endswith("_s")}
    stages.update({f"back-end {k[:-2]}": v for k, v in (report.get("backend_timings") or {}).items()
                   if isinstance(v, (int, float)) and k.endswith("_s")})
    if not stages:
        return None
    fig, ax = plt.subplots(figsize=(12, 0.35 * len(stages) + 1))
    names = list(stages)
    ax.barh(names, [stages[n] for n in names], color=["tab:blue" if n.startswith("front") else "tab:green"
                                                      for n in names])
    ax.invert_yaxis()
    ax.set_xlabel("seconds")
    ax.grid(alpha=0.3, axis="x")
    return fig


def _memory_figure(report: dict):
    import matplotlib.pyplot as plt

    trace = report.get("memory_trace") or {}
    curves = {k: np.asarray(v, float) for k, v in trace.items() if isinstance(v, list) and len(v)}
    if not curves:
        return None
    fig, ax = plt.subplots(figsize=(12, 3.5))
    for name, xy in curves.items():
        ax.plot(xy[:, 0], xy[:, 1], marker=".", lw=1.2, label=name)
    ax.set_xlabel("submaps")
    ax.set_ylabel("RSS (MiB)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    return fig


def _fmt(v) -> str:
    if isinstance(v, float):
        return "inf" if not np.isfinite(v) else f"{v:.4g}"
    return "" if v is None else str(v)


def _summary(run: RunFolder) -> list[tuple[str, str]]:
    r = run.report
    rows = [("input frames", r.get("frames")), ("keyframes", r.get("keyframes")), ("submaps", r.get("submaps")),
            ("backbone", r.get("backbone")), ("calibrated", r.get("calibrated")),
            ("degraded odometry edges", r.get("degraded_edges")),
            ("ATE odometry (keyframes, Sim(3))", r.get("ate_rmse_odometry")),
            ("ATE corrected (keyframes, Sim(3))", r.get("ate_rmse")), ("ATE reduction", r.get("ate_reduction")),
            ("loops accepted / rejected", f"{r['loops_accepted']} / {r['loops_rejected']}"
             if "loops_accepted" in r else None),
            ("front-end frames/s", r.get("frontend_fps")), ("back-end s/submap", r.get("backend_s_per_submap")),
            ("peak RSS (MiB)", r.get("peak_rss_mb")), ("total (s)", r.get("seconds_total"))]
    return [(k, _fmt(v)) for k, v in rows if v is not None]


def render_report(run: RunFolder) -> str:
    """The report's HTML (one string, figures inline)."""
    import matplotlib

    matplotlib.use("Agg")
    import jinja2

    figures = []

    def add(fid: str, title: str, make, caption: str = "") -> None:
        try:
            fig = make()
        except Exception as exc:  # noqa: BLE001 - a figure that cannot be drawn must not lose the report
            log.warning("report: %s not drawn: %s", fid, exc)
            return
        if fig is not None:
            figures.append({"id": fid, "title": title, "png": _png(fig), "caption": caption})

    series = _series(run)
    aligned = " (Sim(3)-aligned to the ground truth)" if run.ground_truth is not None else ""
    add("trajectory", "Trajectory" + aligned, lambda: _trajectory_figure(run, series))
    if run.ground_truth is not None:
        add("ate_over_time", "ATE over time", lambda: _ate_figure(series))
        add("rpe", "Relative pose error", lambda: _rpe_figure(run))
    if run.dem is not None:
        add("dem", "Digital elevation map", lambda: _dem_figure(run))
    add("timings", "Time per stage", lambda: _timings_figure(run.report))
    add("memory", "Memory", lambda: _memory_figure(run.report),
        "Resident memory of each process, sampled every 10 submaps.")
    loops = [{k: _fmt(v) if k not in ("accepted",) else bool(v) for k, v in c.items()} for c in run.loop_candidates]
    loops.sort(key=lambda c: (not c["accepted"], int(c["query"]), int(c["match"])))
    env = jinja2.Environment(autoescape=True)
    return env.from_string(_TEMPLATE).render(
        name=run.name, error=run.report.get("error"), summary=_summary(run), figures=figures, loops=loops,
        n_accepted=sum(c["accepted"] for c in loops), config=json.dumps(run.config, indent=2))


def write_report(run_dir: str | Path, out: str | Path | None = None) -> Path:
    """Write the HTML report of the run in ``run_dir`` (default ``RUN_DIR/report.html``); returns its path.

    Raises:
        InputError: ``run_dir`` is not a run folder.
    """
    run = load_run(run_dir)
    path = Path(out) if out is not None else run.folder / "report.html"
    atomic_write_text(path, render_report(run))
    log.info("report: %s", path)
    return path
