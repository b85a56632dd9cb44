"""Benchmark: generate a 300-frame 640x480 synthetic sequence (render + PNG writing) and print JSON.

Usage: python benchmarks/render_speed.py [--scene loop] [--frames 300] [--out DIR]
"""

from __future__ import annotations

import argparse
import json
import platform
import tempfile
import time

import psutil

from vggt_slam_pp.synthetic import make_scene, write_sequence


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--scene", default="loop", choices=("loop", "figure8"))
    p.add_argument("--frames", type=int, default=300)
    p.add_argument("--width", type=int, default=640)
    p.add_argument("--height", type=int, default=480)
    p.add_argument("--out", default=None)
    args = p.parse_args()
    t0 = time.perf_counter()
    scene = make_scene(args.scene, frames=args.frames, width=args.width, height=args.height)
    t_scene = time.perf_counter() - t0
    with tempfile.TemporaryDirectory() as tmp:
        summary = write_sequence(scene, args.out or tmp)
    summary.update(benchmark="render_speed", scene=args.scene, seconds_scene_setup=t_scene,
                   seconds_wall=time.perf_counter() - t0, cpu=platform.processor() or platform.machine(),
                   cpu_count=psutil.cpu_count(), peak_rss_mb=psutil.Process().memory_info().rss / 2**20)
    print(json.dumps(summary, indent=2))


if __name__ == "__main__":
    main()
