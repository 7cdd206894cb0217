# Shared by the device scripts of benchmarks/gpu (sourced: `source benchmarks/gpu/_lib.sh WORKDIR`): strict unset
# variables, unbuffered Python, OUT required, DRY (1 = a local dry run), a fresh work folder W, the elapsed-time
# stamps `el` / section headers `sec`, and `install_wheels DIR` (the cp312 wheels of DIR and the cp312 pybullet build
# in DIR/pyb312 into /tmp/site, which then leads PYTHONPATH; a failure is printed, not fatal: the checks after say more).
set -u
export PYTHONUNBUFFERED=1
OUT=${OUT:?OUT must be set}
DRY=${DRY:-0}
W=${1:?a work folder}; rm -rf "$W"; mkdir -p "$W"
T0=$(date +%s)
el() { echo "[t=$(( $(date +%s) - T0 )) s]"; }
sec() { echo; echo "==================== $* $(el)"; }
install_wheels() {
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site "$1"/*.whl \
    || echo "SETUP: pip install of the wheels FAILED"
  cp "$1"/pyb312/*.so /tmp/site/ || echo "SETUP: copying the cp312 pybullet build FAILED"
  export PYTHONPATH=/tmp/site:$PWD
}
