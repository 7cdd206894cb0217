"""Pixel training updates/s on a device, through benchmarks/pixel_train_throughput.py's own functions.

    python benchmarks/gpu/pixel_updates.py --device cuda --size 96x64 --only student asym --frames 200 --updates 300 --json OUT.json

``--size WxH`` overrides the experiments' camera (env.camera.width/height; the configs' own is 96x64) by adding to the
benchmark's fixed overrides (its TRACK list); ``--threads`` sets torch's CPU threads (the benchmark uses 1).
Appends one JSON line per contender to ``--json``.
"""

from __future__ import annotations

import os
import sys

THREADS = next((sys.argv[i + 1] for i, a in enumerate(sys.argv) if a == "--threads"), "1")
for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_var] = THREADS

import argparse  # noqa: E402
import json  # noqa: E402
import logging  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
sys.path.insert(0, str(ROOT))

import torch  # noqa: E402

import pixel_train_throughput as bench  # noqa: E402

WHO = {"student": "camera student (DAgger/BC)", "asym": "asymmetric TD3 (camera actor, state critic)",
       "sym": "symmetric pixel TD3 (CNN in the critic too)", "range": "rangefinder TD3"}


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--size", default="96x64")
    ap.add_argument("--only", nargs="+", default=["student", "asym"], choices=list(WHO))
    ap.add_argument("--frames", type=int, default=200)
    ap.add_argument("--updates", type=int, default=40)
    ap.add_argument("--batch", type=int, default=128)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--json", default=None)
    a = ap.parse_args()
    logging.getLogger("torchrl").setLevel(logging.WARNING)
    torch.set_num_threads(a.threads)
    w, h = (int(x) for x in a.size.split("x"))
    bench.TRACK = [*bench.TRACK, f"env.camera.width={w}", f"env.camera.height={h}"]
    device = torch.device(a.device)
    gpu = torch.cuda.get_device_name(0) if device.type == "cuda" else None
    for key in a.only:
        name = WHO[key]
        torch.manual_seed(0)
        t0 = time.perf_counter()
        ov = bench.CONTENDERS[name]
        try:
            f, u = bench.student(a.frames, a.updates, a.batch, device) if ov is None else \
                bench.actor_critic(ov, a.frames, a.updates, a.batch, device)
            err = None
        except Exception as e:  # noqa: BLE001
            f = u = float("nan")
            err = f"{type(e).__name__}: {e}"
        row = {"contender": name, "device": str(device), "gpu": gpu, "size": a.size, "batch": a.batch,
               "threads": a.threads, "updates": a.updates, "frames": a.frames, "env_frames_per_s": f,
               "updates_per_s": u, "wall_s": time.perf_counter() - t0, "error": err}
        print(f"PIXEL {name} | {a.size} | {device} ({a.threads} thr) | env {f:.0f} frames/s | {u:.1f} updates/s"
              f" | {row['wall_s']:.0f} s" + (f" | ERROR {err}" if err else ""), flush=True)
        if a.json:
            with open(a.json, "a") as fh:
                fh.write(json.dumps(row) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
