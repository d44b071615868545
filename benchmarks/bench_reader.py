"""Training reader speed: samples/s on one core from the decoded-frame cache (target 1,000),
and the time to build the cache, on freshly recorded Town01 episodes.

    .venv/bin/python benchmarks/bench_reader.py [--json] [--frames 600]
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time

import torch

from bid_model.config import small
from bid_model.recordings import open_recordings
from bid_sim.record import record


def bench_reader(frames: int = 600, agent: str = "lanefollow") -> dict:
    torch.set_num_threads(1)
    hw = small().model.frame_hw
    with tempfile.TemporaryDirectory() as tmp:
        record("01", 2, ("ClearNoon", "WetNoon"), ("normal",), 0, 2, tmp, agent=agent,
               max_steps=frames // 2, progress=False)
        t0 = time.perf_counter()
        train, val, desc = open_recordings(tmp, hw, 0.5, 0)
        build_s = time.perf_counter() - t0
        n = 0
        t0 = time.process_time()
        for _ in range(3):
            for ds in (train, val):
                for i in range(len(ds)):
                    ds[i]
                    n += 1
        cpu = time.process_time() - t0
    return {"frame_hw": list(hw), "samples": desc["samples"], "cache_build_s": round(build_s, 2),
            "reader_samples_per_s_per_core": round(n / cpu, 1), "reader_target_ratio": round(n / cpu / 1000.0, 2)}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--json", action="store_true")
    p.add_argument("--frames", type=int, default=600)
    p.add_argument("--agent", default="lanefollow", help="who drives the recorded episodes")
    args = p.parse_args()
    r = bench_reader(args.frames, args.agent)
    if args.json:
        print(json.dumps(r, indent=1))
    else:
        print(f"reader: {r['reader_samples_per_s_per_core']} samples/s per core from the cache "
              f"({r['samples']} samples at {r['frame_hw'][0]}x{r['frame_hw'][1]}, cache built in "
              f"{r['cache_build_s']} s; target 1000)")


if __name__ == "__main__":
    main()
