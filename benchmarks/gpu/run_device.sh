#!/bin/bash
# GPU checks of the camera path on a lent GPU machine: EGL vs TinyRenderer frames (PNG + JSON),
# frames/s, the CUDA smoke test, pixel-training updates/s on cuda vs cpu. Run from a snapshot of the repo (git archive
# HEAD into .devsnap) with, beside it, ../.whl (cp312 wheels: torchrl, tensordict, gymnasium, hydra-core, omegaconf and
# their needs; ../.whl/pyb312/: pybullet 3.2.7 built from source for cp312, since PyPI has no cp312 binary) and
# ../.gl (Debian's libegl1 libglvnd0 libopengl0 libgl1 libglx0 libgles2 .debs), OUT set:
#   set -o pipefail; cd .devsnap && bash benchmarks/gpu/run_device.sh 2>&1 | tee $OUT/log.txt
# Figures of 2026-11-26 (H200): torcsrl/envs/camera.py's docstring and the README's "Drivers that see".
# DRY=1: local dry run (no install, tiny sizes; GPU parts report unavailable / skip).
source "$(dirname "$0")/_lib.sh" /tmp/dc_work

sec "A. setup"
if [ "$DRY" != 1 ]; then
  for f in ../.gl/*.deb; do dpkg -x "$f" /; done; ldconfig
  install_wheels ../.whl
  if [ ! -e /usr/share/glvnd/egl_vendor.d/10_nvidia.json ] && [ -e /usr/local/nvidia/share/glvnd/egl_vendor.d/10_nvidia.json ]; then
    export __EGL_VENDOR_LIBRARY_FILENAMES=/usr/local/nvidia/share/glvnd/egl_vendor.d/10_nvidia.json
  fi
  FR=300; REP=2; UP_GPU=300; UP_CPU=40; PF=200
else
  export PYTHONPATH=$PWD
  FR=20; REP=1; UP_GPU=4; UP_CPU=3; PF=140
fi
echo "PYTHONPATH=$PYTHONPATH __EGL_VENDOR_LIBRARY_FILENAMES=${__EGL_VENDOR_LIBRARY_FILENAMES:-unset} snapshot=$(cat SNAPSHOT_COMMIT 2>/dev/null)"
nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader 2>&1 | head -2
ls /usr/share/glvnd/egl_vendor.d/ /usr/local/nvidia/share/glvnd/egl_vendor.d/ 2>&1 | head -8
ldconfig -p | grep -i -E 'libEGL|libOpenGL|libGLX_nvidia' | head -8
lscpu | grep -E '^Model name|^CPU\(s\)' ; uptime
timeout 120 python3 -W always::UserWarning - <<'EOF' 2>&1 | tee $W/versions.txt
import sys, importlib
print("python", sys.version.split()[0])
for m in ("numpy", "torch", "tensordict", "torchrl", "gymnasium", "pybullet", "hydra", "omegaconf", "cv2"):
    try:
        mod = importlib.import_module(m)
        print(f"{m} {getattr(mod, '__version__', '?')} from {getattr(mod, '__file__', '?')}")
    except Exception as e:
        print(f"IMPORT FAILED {m}: {type(e).__name__}: {e}")
import torch
print("cuda available", torch.cuda.is_available(), torch.cuda.get_device_name(0) if torch.cuda.is_available() else "")
try:
    import pybullet as p, pkgutil
    print("pybullet numpy", p.isNumpyEnabled(), "eglRenderer", pkgutil.get_loader("eglRenderer"))
except Exception as e:
    print("pybullet check failed", e)
import torcsrl; print("torcsrl from", torcsrl.__file__)
EOF

sec "B. EGL vs tiny frames + frames/s (hood camera, hairpins)"
for r in tiny egl; do
  timeout 90 python3 benchmarks/gpu/egl_frames.py $r $W --frames $FR --repeats $REP
  echo "egl_frames $r rc=$?"
done
timeout 60 python3 benchmarks/gpu/egl_compare.py $W; echo "egl_compare rc=$?"
cp $W/egl_vs_tiny.png $W/frames_tiny.npz $W/frames_egl.npz $OUT/ 2>/dev/null

sec "C. CUDA smoke test"
timeout 180 python3 -m pytest -q -p no:cacheprovider -rA tests/test_train_device.py::test_cuda_smoke 2>&1 | tail -25
echo "SMOKE rc=${PIPESTATUS[0]}" | tee $W/smoke_rc.txt

sec "D. pixel training updates/s, batch 128 (GPU vs CPU on this machine)"
CUDA=$(python3 -c "import torch; print(int(torch.cuda.is_available()))" 2>/dev/null || echo 0)
for size in 96x64 64x64; do
  if [ "$CUDA" = 1 ]; then
    timeout 120 python3 benchmarks/gpu/pixel_updates.py --device cuda --size $size --only student asym --frames $PF --updates $UP_GPU --json $W/pixel.jsonl
    echo "pixel cuda $size rc=$?"
  else
    echo "pixel cuda $size: SKIPPED (no CUDA here)"
  fi
  timeout 120 python3 benchmarks/gpu/pixel_updates.py --device cpu --size $size --only student asym --frames $PF --updates $UP_CPU --json $W/pixel.jsonl
  echo "pixel cpu $size rc=$?"
done
NT=$(nproc)
timeout 90 python3 benchmarks/gpu/pixel_updates.py --device cpu --threads $NT --size 96x64 --only asym --frames $PF --updates $UP_CPU --json $W/pixel.jsonl
echo "pixel cpu $NT threads rc=$?"

sec "E. benchmarks/camera_throughput.py (tiny + EGL, one thread)"
timeout 150 python3 benchmarks/camera_throughput.py --frames $(( FR < 200 ? FR : 200 )) --repeats $REP --peers /nonexistent
echo "camera_throughput rc=$?"

sec "F. summary"
python3 - "$W" "$OUT" <<'EOF'
import json, os, sys
w, out = sys.argv[1], sys.argv[2]
def load(name):
    f = os.path.join(w, name)
    return json.load(open(f)) if os.path.exists(f) else None
res = {"egl_compare": load("egl_compare.json"), "rates_tiny": load("rates_tiny.json"), "rates_egl": load("rates_egl.json")}
pj = os.path.join(w, "pixel.jsonl")
res["pixel"] = [json.loads(l) for l in open(pj)] if os.path.exists(pj) else []
sf = os.path.join(w, "smoke_rc.txt")
res["smoke"] = open(sf).read().strip() if os.path.exists(sf) else None
vf = os.path.join(w, "versions.txt")
res["versions"] = open(vf).read().splitlines() if os.path.exists(vf) else None
json.dump(res, open(os.path.join(out, "results.json"), "w"), indent=1)
print("frames/s (hood camera, hairpins, one thread, best of runs):")
for r in ("tiny", "egl"):
    d = res[f"rates_{r}"]
    print(f"  {r:5s}", "  ".join(f"{k[4:]}: {v:.0f}" for k, v in d.items() if k.startswith("fps_")) if d else "  (none)")
for k, v in (res["egl_compare"] or {}).items():
    print(f"  diff {k}: mean |grey| {v['mean_abs_diff_grey']:.2f}, depth rel median {v['depth_rel_diff_median']:.1e}")
print("pixel updates/s:")
for r in res["pixel"]:
    print(f"  {r['contender'][:28]:28s} {r['size']:6s} {r['device']:5s} {r['threads']:2d} thr: {r['updates_per_s']:8.1f} upd/s"
          f"  (env {r['env_frames_per_s']:.0f} frames/s){'  ERR ' + r['error'] if r['error'] else ''}")
print("smoke:", res["smoke"])
EOF
echo "DONE $(el)"
