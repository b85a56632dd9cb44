"""The noisy oracle VGGT through the whole system (back-end on) against the simulated backbone with the
same noise, on a rendered block loop (issue 22).

    python benchmarks/oracle_vs_simulated.py [--seeds 0 1 2] [--out runs/oracle_vs_simulated]

Prints per seed the odometry and corrected ATE (Sim(3)-aligned keyframes, metres) and the accepted
loops of both; writes them to ``OUT/summary.json``. About a minute per seed on 2 cores.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from vggt_slam_pp.frontend.backbones.oracle import oracle_backbone
from vggt_slam_pp.frontend.backbones.simulated import SimulatedNoise
from vggt_slam_pp.frontend.frontend import FrontendConfig
from vggt_slam_pp.frontend.keyframes import KeyframeConfig
from vggt_slam_pp.io import open_source
from vggt_slam_pp.pipeline import BackboneConfig, RunConfig, run
from vggt_slam_pp.synthetic import make_scene, write_sequence
from vggt_slam_pp.synthetic.oracle import OracleNoise


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    p.add_argument("--out", type=Path, default=Path("runs/oracle_vs_simulated"))
    args = p.parse_args()
    seq = args.out / "sequence"
    if not (seq / "groundtruth.txt").is_file():
        write_sequence(make_scene("loop", frames=300, width=320, height=240, seed=0), seq)
    source = open_source(seq)
    frontend = FrontendConfig(keyframes=KeyframeConfig(tau_disparity=20.0), submap_size=8)
    n = SimulatedNoise()
    rows = []
    for seed in args.seeds:
        noise = OracleNoise(n.depth_noise, n.scale_error, n.rot_noise_deg, n.trans_noise)
        o = run(source, RunConfig(backbone=BackboneConfig(name="vggt"), frontend=frontend), args.out / f"oracle{seed}",
                backbone=oracle_backbone(source, noise=noise, seed=seed))
        s = run(source, RunConfig(backbone=BackboneConfig(name="simulated", seed=seed), frontend=frontend),
                args.out / f"simulated{seed}")
        row = {"seed": seed, **{f"{k}_{m}": r[m] for k, r in (("oracle", o), ("simulated", s))
                                for m in ("ate_rmse_odometry", "ate_rmse", "loops_accepted")}}
        rows.append(row)
        print(f"seed {seed}: oracle {o['ate_rmse_odometry']:.3f} -> {o['ate_rmse']:.3f} m ({o['loops_accepted']} loops), "
              f"simulated {s['ate_rmse_odometry']:.3f} -> {s['ate_rmse']:.3f} m ({s['loops_accepted']} loops)",
              flush=True)
    (args.out / "summary.json").write_text(json.dumps(rows, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
