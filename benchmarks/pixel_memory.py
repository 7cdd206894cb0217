"""Replay memory of camera transitions: bytes per transition, and how many fit in 8 GiB of RAM and on disk.

    python benchmarks/pixel_memory.py [--rows 20000] [--sizes 64 84] [--gib 8] [--frame-stack 1 3]

Measured on real buffers, not only computed: for each camera resolution and observation set (the camera actor's
``pixels + telemetry``, and the asymmetric critic's ``+ rangefinder + state``), real race-env steps (random actions,
hood camera) are written into a :class:`torcsrl.utils.replay.ReplayBuffer` of ``--rows`` transitions, and

* **RAM**: the growth of this process's resident memory (``VmRSS``) while the buffer fills (``storage=ram``);
* **disk**: the allocated blocks of the memory-mapped files (``storage=disk``, ``st_blocks``) after the same writes;
* **formula**: :attr:`ReplayBuffer.bytes_per_transition` (one row: ONE uint8 frame, the vectors, action, reward,
  flags, a pointer) + one final observation per finished episode (episodes of ``--episode`` steps);
* **peer**: TorchRL's ``LazyTensorStorage`` holding the same transitions the usual way (each with its next
  observation), its tensors' bytes — the ratio is what storing each frame once saves.

``--frame-stack K`` (``frame_stack=K`` runs: the actor sees K frames): the steps come from a ``FrameStack`` env and
the ring rebuilds the stacks when sampling (``history``), so its rows hold one frame; the peer holds the K-frame
stacks of obs and next obs.

Transitions that fit in ``--gib`` GiB = that budget / the measured bytes per transition. Each stored pixel stays
uint8 (checked). The machine may be shared: memory figures do not depend on the load.
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import torch  # noqa: E402
from tensordict import TensorDict  # noqa: E402

from torcsrl.utils.replay import ReplayBuffer  # noqa: E402

SETS = {"camera (actor)": ["pixels", "telemetry"], "camera + critic (asym)": ["pixels", "telemetry", "rangefinder", "state"]}


def rss_bytes() -> int:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) * 1024
    raise RuntimeError("no VmRSS in /proc/self/status")


def disk_bytes(path: Path) -> int:
    """Allocated bytes (blocks actually written, not the files' apparent sizes) under ``path``."""
    return sum(f.stat().st_blocks * 512 for f in path.rglob("*") if f.is_file())


def real_steps(size: int, steps: int, episode: int, seed: int = 0, frames: int = 1) -> TensorDict:
    """``steps`` real race-env transitions (one car, random actions, every sensor of both sets; ``frames`` > 1: pixels
    stacked by :class:`torcsrl.transforms.FrameStack`), ``[steps]``."""
    from torchrl.envs import Compose

    from torcsrl.envs import make_env
    from torcsrl.transforms import FrameStack, LeanTransformedEnv

    env = make_env(sensors=("pixels", "telemetry", "rangefinder", "state"), camera={"height": size, "width": size}, track="oval",
                   seed=seed, max_steps=episode)
    if frames > 1:
        env = LeanTransformedEnv(env, Compose(FrameStack(frames, ["pixels"])))
    try:
        torch.manual_seed(seed)
        ro = env.rollout(steps, break_when_any_done=False)  # random actions; resets inside at episode ends
    finally:
        env.close()
    return ro.reshape(-1)


def fill(buf: ReplayBuffer, data: TensorDict, rows: int) -> None:
    """Write ``rows`` transitions, cycling through ``data`` in chunks (as a long run would)."""
    n, written = data.shape[0], 0
    while written < rows:
        k = min(n, rows - written)
        buf.extend(data[:k])
        written += k


def peer_bytes(data: TensorDict, keys: list[str], rows: int) -> float:
    """Bytes per transition of TorchRL's LazyTensorStorage holding obs, action, reward, flags and the next obs."""
    from torchrl.data import LazyTensorStorage

    sel = data.select(*keys, "action", *[("next", k) for k in (*keys, "reward", "done", "terminated", "truncated")])
    st = LazyTensorStorage(rows)
    st.set(torch.arange(min(rows, sel.shape[0])), sel[: min(rows, sel.shape[0])])
    return sum(t.element_size() * t[0].numel() for t in st._storage.values(True, True))


def measure(size: int, keys: list[str], data: TensorDict, rows: int, episode: int, frames: int = 1) -> dict:
    import gc

    gc.collect()
    hist = {"pixels": frames} if frames > 1 else None
    # RAM: resident growth while the ring fills
    before = rss_bytes()
    ram = ReplayBuffer(rows, 128, keys, history=hist)
    fill(ram, data, rows)
    ram_growth = rss_bytes() - before
    assert ram._rows["pixels"].dtype == torch.uint8 and ram.sample(4)["next", "pixels"].dtype == torch.uint8
    row, final = ram.bytes_per_transition, ram.bytes_per_final
    del ram
    gc.collect()
    # disk: blocks of the memory-mapped files after the same writes
    tmp = Path(tempfile.mkdtemp(prefix="pixmem_"))
    try:
        disk = ReplayBuffer(rows, 128, keys, storage="disk", path=tmp, history=hist)
        fill(disk, data, rows)
        for t in disk._rows.values(True, True):  # flush the pages to the files
            if hasattr(t, "_handler") or hasattr(t, "flush"):
                getattr(t, "flush", lambda: None)()
        on_disk = disk_bytes(tmp)
        del disk
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    formula = row + final / episode
    return {"row": row, "final": final, "formula": formula, "ram": ram_growth / rows, "disk": on_disk / rows,
            "peer": peer_bytes(data, keys, rows)}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rows", type=int, default=20000, help="transitions written per buffer")
    ap.add_argument("--sizes", type=int, nargs="+", default=[64, 84], help="camera resolutions [px]")
    ap.add_argument("--steps", type=int, default=1000, help="real env steps collected per resolution (cycled)")
    ap.add_argument("--episode", type=int, default=1000, help="episode length [steps] (one final frame per episode)")
    ap.add_argument("--gib", type=float, default=8.0, help="memory budget [GiB]")
    ap.add_argument("--frame-stack", type=int, nargs="+", default=[1], help="frames per stack (frame_stack=K) [frames]")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    budget = args.gib * 2**30
    free = shutil.disk_usage(tempfile.gettempdir()).free
    print(f"# pixel replay memory: {args.rows} transitions per buffer, real race-env steps (oval, random actions), "
          f"episodes of {args.episode} steps; load {os.getloadavg()[0]:.2f} (machine may be shared); free disk {free / 2**30:.0f} GiB")
    print("| camera | frames | observation set | bytes/transition (row + final/episode) | RAM measured [B] | disk measured [B] | "
          f"in {args.gib:g} GiB RAM | in {args.gib:g} GiB disk | on this disk ({free / 2**30:.0f} GiB free) | "
          "TorchRL LazyTensorStorage [B] | ratio |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for size, k in [(size, k) for size in args.sizes for k in args.frame_stack]:
        t0 = time.perf_counter()
        data = real_steps(size, args.steps, args.episode, frames=k)
        for name, keys in SETS.items():
            m = measure(size, keys, data, args.rows, args.episode, frames=k)
            print(f"| {size}x{size} | {k} | {name}: {'+'.join(keys)} | {m['formula']:,.0f} ({m['row']:,} + {m['final']:,}/{args.episode}) | "
                  f"{m['ram']:,.0f} | {m['disk']:,.0f} | {budget / m['ram'] / 1e6:.2f} M | {budget / m['disk'] / 1e6:.2f} M | "
                  f"{free / m['disk'] / 1e6:.1f} M | {m['peer']:,.0f} | {m['peer'] / m['formula']:.2f}x |")
        print(f"# {size}x{size}: collected and measured in {time.perf_counter() - t0:.0f} s", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
