"""Front-end frames/s with the live viewer on and off (issue 20's target: on >= 0.9x off).

    python benchmarks/viewer_fps.py [--frames 600] [--repeats 3] [--client] [--workdir runs/bench_viewer]

Renders (once, cached in ``--workdir``) the demo's synthetic block loop, then runs the demo's configuration
on it ``--repeats`` times with ``run(..., viewer=LiveViewer())`` and without, alternating, and prints the
front-end's frames/s (``report.json``'s ``frontend_fps``) of each run, the medians and their ratio as JSON.
``--client``: a headless Chromium (Debian's ``chromium``) has the viewer's page open during the run, so the
scene is also streamed over the websocket (the browser renders in software on the same cores: a pessimistic
case; a person's browser would normally draw on a GPU); ``--client-idle`` runs it at idle priority.
"""

from __future__ import annotations

import argparse
import json
import shutil
import statistics
import subprocess
import sys
from pathlib import Path

CHROMIUM_ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                 "--disable-background-networking", "--disable-component-update", "--disable-sync",
                 "--use-angle=swiftshader", "--enable-unsafe-swiftshader"]


def main() -> int:
    from vggt_slam_pp.io import open_source
    from vggt_slam_pp.pipeline import RunConfig, run
    from vggt_slam_pp.synthetic import make_scene, write_sequence
    from vggt_slam_pp.viz.live import LiveViewer

    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--frames", type=int, default=600)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--client", action="store_true", help="a headless Chromium shows the page during the run")
    p.add_argument("--client-idle", action="store_true",
                   help="run that Chromium at idle priority (as if it drew on another machine or a GPU)")
    p.add_argument("--port", type=int, default=8141)
    p.add_argument("--workdir", type=Path, default=Path("runs/bench_viewer"))
    args = p.parse_args()
    seq = args.workdir / f"loop_{args.frames}"
    if not (seq / "groundtruth.txt").is_file():
        write_sequence(make_scene("loop", frames=args.frames, seed=0, width=320, height=240), seq)
    source, config = open_source(seq), RunConfig.preset("synthetic")
    chromium = shutil.which("chromium")
    if args.client and chromium is None:
        print("--client needs Debian's chromium", file=sys.stderr)
        return 2
    fps: dict[str, list[float]] = {"on": [], "off": []}
    drawn = None
    for _ in range(args.repeats):
        for mode in ("on", "off"):
            viewer = LiveViewer(port=args.port) if mode == "on" else None
            browser = None
            if viewer is not None and args.client:
                idle = ["chrt", "--idle", "0"] if args.client_idle else []
                browser = subprocess.Popen([*idle, chromium, *CHROMIUM_ARGS, "--user-data-dir=" + str(args.workdir / "chrome"),
                                            "--remote-debugging-port=0", viewer.url],
                                           stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
            try:
                report = run(source, config, args.workdir / f"run_{mode}", viewer=viewer)
            finally:
                if browser is not None:
                    browser.kill()
                    browser.wait()
                if viewer is not None:
                    drawn = viewer.close()
            fps[mode].append(report["frontend_fps"])
            print(f"viewer {mode}: {report['frontend_fps']:.1f} frames/s", file=sys.stderr)
    on, off = statistics.median(fps["on"]), statistics.median(fps["off"])
    print(json.dumps({"frames": len(source), "repeats": args.repeats, "client": args.client,
                      "client_idle": args.client_idle, "fps_on": fps["on"],
                      "fps_off": fps["off"], "median_on": on, "median_off": off, "ratio": on / off,
                      "viewer_drew": {k: v for k, v in (drawn or {}).items() if k != "nodes"}, "target_ratio": 0.9},
                     indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
