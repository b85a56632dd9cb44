"""A suite's tables and plots, in the layout of the paper's tables: configurations as rows, sequences as
columns plus their average; a cell is the ATE (metres: the corrected trajectory's with the back-end, the
odometry's without) as mean +- std over the runs, ``fail`` where every run failed and ``k/n failed``
beside the figure where some did. Written as ``table.md``, ``table.csv``, ``table.tex``, one trajectory
plot per sequence (``plots/SEQUENCE.png``: the ground truth and each configuration's first run) and a
summary plot (``plots/summary.png``).
"""

from __future__ import annotations

import csv
import io
import logging
from pathlib import Path

import numpy as np

from vggt_slam_pp.io.trajectory import atomic_write_text

log = logging.getLogger(__name__)

__all__ = ["Cell", "aggregate", "write_tables", "write_plots"]


class Cell:
    """One configuration on one sequence over its runs."""

    def __init__(self, values: list[float], failed: int, runs: int) -> None:
        self.values, self.failed, self.runs = values, failed, runs

    @property
    def mean(self) -> float | None:
        return float(np.mean(self.values)) if self.values else None

    @property
    def std(self) -> float | None:
        return float(np.std(self.values, ddof=1)) if len(self.values) > 1 else (0.0 if self.values else None)

    def text(self, pm: str = "±") -> str:
        if not self.values:
            return "fail" if self.failed else "-"
        s = f"{self.mean:.3f} {pm} {self.std:.3f}" if self.runs > 1 else f"{self.mean:.3f}"
        return s + (f" ({self.failed}/{self.runs} failed)" if self.failed else "")


def _column(r: dict) -> str:
    return f"{r['dataset']}/{r['sequence']}" if r["dataset"] != r["sequence"] else r["dataset"]


def aggregate(results: list[dict]) -> tuple[list[str], list[str], dict[tuple[str, str], Cell]]:
    """(configurations, sequence columns, cells) from every task's result, in the suite's order."""
    configs, columns, groups = [], [], {}
    for r in results:
        c, col = r["config"], _column(r)
        if c not in configs:
            configs.append(c)
        if col not in columns:
            columns.append(col)
        groups.setdefault((c, col), []).append(r)
    cells = {}
    for key, rs in groups.items():
        ok = [r["ate"] for r in rs if r.get("error") is None and r.get("ate") is not None]
        cells[key] = Cell([float(v) for v in ok], sum(r.get("error") is not None for r in rs), len(rs))
    return configs, columns, cells


def _average(configs, columns, cells) -> dict[str, str]:
    """Per configuration: the mean of its per-sequence means, over the sequences where it has a figure
    (marked with how many when that is not all)."""
    out = {}
    for c in configs:
        means = [cells[(c, col)].mean for col in columns if (c, col) in cells and cells[(c, col)].mean is not None]
        n = sum((c, col) in cells for col in columns)
        out[c] = "-" if not means else f"{np.mean(means):.3f}" + ("" if len(means) == n else f" ({len(means)}/{n})")
    return out


def write_tables(results: list[dict], out: Path) -> dict[str, Path]:
    """``table.md``, ``table.csv`` and ``table.tex`` in ``out``; returns their paths."""
    configs, columns, cells = aggregate(results)
    avg = _average(configs, columns, cells)
    runs = max((cells[k].runs for k in cells), default=0)
    md = [f"ATE (m, Sim(3)-aligned keyframes), mean ± std over {runs} run(s)", "",
          "| configuration | " + " | ".join(columns) + " | average |",
          "| --- | " + " | ".join("---" for _ in columns) + " | --- |"]
    for c in configs:
        md.append(f"| {c} | " + " | ".join(cells[(c, col)].text() if (c, col) in cells else "-" for col in columns)
                  + f" | {avg[c]} |")
    buf = io.StringIO()
    w = csv.writer(buf)
    w.writerow(["configuration", "sequence", "ate_mean", "ate_std", "runs", "failed", "values"])
    for c in configs:
        for col in columns:
            if (c, col) in cells:
                cell = cells[(c, col)]
                w.writerow([c, col, cell.mean, cell.std, cell.runs, cell.failed, " ".join(f"{v:.6f}" for v in cell.values)])

    def tex(s: str) -> str:
        return s.replace("_", r"\_").replace("%", r"\%").replace("&", r"\&")

    lines = [r"\begin{tabular}{l" + "c" * (len(columns) + 1) + "}", r"\toprule",
             "Configuration & " + " & ".join(tex(col) for col in columns) + r" & Avg. \\", r"\midrule"]
    for c in configs:
        row = [cells[(c, col)].text(pm=r"$\pm$") if (c, col) in cells else "-" for col in columns]
        lines.append(tex(c) + " & " + " & ".join(row) + f" & {avg[c]} " + r"\\")
    lines += [r"\bottomrule", r"\end{tabular}"]
    paths = {"md": out / "table.md", "csv": out / "table.csv", "tex": out / "table.tex"}
    atomic_write_text(paths["md"], "\n".join(md) + "\n")
    atomic_write_text(paths["csv"], buf.getvalue())
    atomic_write_text(paths["tex"], "\n".join(lines) + "\n")
    return paths


def write_plots(results: list[dict], out: Path) -> list[Path]:
    """A trajectory plot per sequence (ground truth and each configuration's first finished run, Sim(3)-
    aligned, seen from above: the plane of most motion) and a summary bar chart of the table; returns the files written."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from vggt_slam_pp.errors import VggtSlamError
    from vggt_slam_pp.viz.run_folder import aligned_positions, load_run, motion_axes

    folder = out / "plots"
    folder.mkdir(parents=True, exist_ok=True)
    configs, columns, cells = aggregate(results)
    written = []
    for col in columns:
        fig, ax = plt.subplots(figsize=(6, 6))
        truth_drawn, plane = False, None
        for c in configs:
            first = next((r for r in results if r["config"] == c and _column(r) == col and r.get("error") is None), None)
            if first is None:
                continue
            try:
                run = load_run(Path(first["folder"]) / "run")
            except VggtSlamError as exc:
                log.warning("plot %s: %s", col, exc)
                continue
            _, p, truth, _ = aligned_positions(run.corrected or run.odometry, run.ground_truth)
            if plane is None:  # the plane of most motion (KITTI's ground is x-z, EuRoC's x-y)
                ref = truth if truth is not None else p
                mean, axes = motion_axes(ref)
                plane = (mean, axes[:2])
            if truth is not None and not truth_drawn:
                q = (truth - plane[0]) @ plane[1].T
                ax.plot(q[:, 0], q[:, 1], "k-", lw=1.5, label="ground truth")
                truth_drawn = True
            q = (p - plane[0]) @ plane[1].T
            ax.plot(q[:, 0], q[:, 1], lw=1, label=f"{c} (seed {first['seed']})")
        ax.set_aspect("equal", adjustable="datalim")
        ax.set_title(col)
        ax.grid(alpha=0.3)
        if ax.lines:
            ax.legend(fontsize=8)
        path = folder / f"{col.replace('/', '__')}.png"
        fig.savefig(path, dpi=90, bbox_inches="tight")
        plt.close(fig)
        written.append(path)
    fig, ax = plt.subplots(figsize=(max(6, 1.2 * len(columns) * max(len(configs), 1) / 2), 4))
    width = 0.8 / max(len(configs), 1)
    x = np.arange(len(columns))
    for k, c in enumerate(configs):
        means = [cells[(c, col)].mean if (c, col) in cells and cells[(c, col)].mean is not None else np.nan
                 for col in columns]
        stds = [cells[(c, col)].std if (c, col) in cells and cells[(c, col)].std is not None else 0.0 for col in columns]
        ax.bar(x + k * width - 0.4 + width / 2, means, width, yerr=stds, capsize=3, label=c)
    ax.set_xticks(x, columns, rotation=20, ha="right")
    ax.set_ylabel("ATE (m), mean ± std")
    positive = [cells[k].mean for k in cells if cells[k].mean is not None and cells[k].mean > 0]
    if positive and max(positive) > 10 * min(positive):
        ax.set_yscale("log")  # figures of several orders of magnitude side by side
    ax.grid(alpha=0.3, axis="y")
    if positive:
        ax.legend(fontsize=8)
    else:
        ax.set_title("no run has an ATE (failed, or no ground truth)")
    path = folder / "summary.png"
    fig.savefig(path, dpi=90, bbox_inches="tight")
    plt.close(fig)
    written.append(path)
    return written
