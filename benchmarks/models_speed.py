"""Speed, peak memory and FLOPs of one VGGT-1B / DINOv2 forward (random weights).

    python benchmarks/models_speed.py                 # CPU: VGGT-1B S=2 and S=8 at 518x294, DINOv2 ViT-B/14 518x518
    python benchmarks/models_speed.py --gpu           # adds VGGT-1B S=32 on CUDA (bf16/fp16 autocast)
    python benchmarks/models_speed.py --case vggt --frames 2 --device cpu   # one case, in this process

Every case runs in its own process so that its peak memory (ru_maxrss on CPU, max_memory_allocated on
GPU) is its own. FLOPs are counted with ``torch.utils.flop_counter`` on the ``meta`` device (no compute):
matmuls, convolutions and attention, multiply-add = 2 FLOPs. Prints a table and, with ``--json``,
writes the figures.
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time

import torch


def count_flops(case: str, frames: int, hw: tuple[int, int]) -> float:
    from torch.utils.flop_counter import FlopCounterMode

    from vggt_slam_pp.models import build_dinov2, build_vggt

    with torch.device("meta"):
        if case == "vggt":
            model, x = build_vggt({}).eval(), torch.rand(1, frames, 3, *hw)
        else:
            model, x = build_dinov2("dinov2_vitb14").eval(), torch.rand(1, 3, *hw)
    model.requires_grad_(False)
    counter = FlopCounterMode(display=False)
    with counter:
        model(x)
    return float(counter.get_total_flops())


def run_case(case: str, frames: int, hw: tuple[int, int], device: str, repeats: int) -> dict:
    from vggt_slam_pp.models import build_dinov2, build_vggt
    from vggt_slam_pp.models.runtime import autocast_dtype, inference_context

    torch.manual_seed(0)
    t0 = time.perf_counter()
    model = (build_vggt({}) if case == "vggt" else build_dinov2("dinov2_vitb14")).eval().to(device)
    build_s = time.perf_counter() - t0
    shape = (1, frames, 3, *hw) if case == "vggt" else (1, 3, *hw)
    x = torch.rand(*shape, device=device)
    times = []
    if device.startswith("cuda"):
        torch.cuda.reset_peak_memory_stats()
    for _ in range(repeats + (1 if device.startswith("cuda") else 0)):
        if device.startswith("cuda"):
            torch.cuda.synchronize()
        t = time.perf_counter()
        with inference_context(device):
            model(x)
        if device.startswith("cuda"):
            torch.cuda.synchronize()
        times.append(time.perf_counter() - t)
    if device.startswith("cuda"):
        times = times[1:]  # first call: kernel selection / warm-up
    out = {"case": case, "frames": frames, "hw": list(hw), "device": device,
           "dtype": str(autocast_dtype(device) or torch.float32).replace("torch.", ""),
           "seconds": min(times), "seconds_all": times, "build_seconds": build_s,
           "threads": torch.get_num_threads()}
    if device.startswith("cuda"):
        out["peak_gpu_gib"] = torch.cuda.max_memory_allocated() / 2**30
        out["gpu"] = torch.cuda.get_device_name()
    out["peak_rss_gib"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20
    return out


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--case", choices=("vggt", "dinov2"))
    p.add_argument("--frames", type=int, default=2)
    p.add_argument("--height", type=int, default=None)
    p.add_argument("--width", type=int, default=518)
    p.add_argument("--device", default="cpu")
    p.add_argument("--repeats", type=int, default=1)
    p.add_argument("--gpu", action="store_true", help="also run VGGT-1B with 32 frames on CUDA")
    p.add_argument("--json", help="write all figures to this file")
    args = p.parse_args()
    if args.case:  # one case in this process
        hw = (args.height or (294 if args.case == "vggt" else 518), args.width)
        print(json.dumps(run_case(args.case, args.frames, hw, args.device, args.repeats)))
        return 0
    cases = [("vggt", 2, (294, 518), "cpu"), ("vggt", 8, (294, 518), "cpu"), ("dinov2", 1, (518, 518), "cpu")]
    if args.gpu:
        cases.append(("vggt", 32, (294, 518), "cuda"))
    results = []
    for case, frames, hw, device in cases:
        cmd = [sys.executable, __file__, "--case", case, "--frames", str(frames), "--height", str(hw[0]),
               "--width", str(hw[1]), "--device", device, "--repeats", "3" if device == "cuda" else "1"]
        proc = subprocess.run(cmd, capture_output=True, text=True, check=False)
        if proc.returncode != 0:
            print(f"{case} S={frames} on {device} failed:\n{proc.stderr[-2000:]}", file=sys.stderr)
            continue
        r = json.loads(proc.stdout.strip().splitlines()[-1])
        r["gflops"] = count_flops(case, frames, hw) / 1e9
        r["achieved_gflops_per_s"] = r["gflops"] / r["seconds"]
        results.append(r)
        mem = f"{r['peak_gpu_gib']:.2f} GiB GPU" if "peak_gpu_gib" in r else f"{r['peak_rss_gib']:.2f} GiB RSS"
        print(f"{case:6s} S={frames:<3d} {hw[0]}x{hw[1]} {device:4s} {r['dtype']:8s} {r['seconds']:8.2f} s  "
              f"peak {mem}  {r['gflops']:9.1f} GFLOP  ({r['achieved_gflops_per_s']:.0f} GFLOP/s, "
              f"{r['threads']} threads)", flush=True)
    if args.json:
        with open(args.json, "w") as f:
            json.dump(results, f, indent=2)
    return 0


if __name__ == "__main__":
    sys.exit(main())
