#!/bin/bash
# The device tests of the training loop on a lent GPU machine: every algorithm with device=cuda (tests/test_train_device.py,
# the CUDA smoke tests skip without a GPU). Run from the repository root with the cp312 wheels beside it (see run_device.sh):
#   WHL=.whl GL=.gl bash benchmarks/gpu/device_tests.sh        (the device tool: carry [.whl, .gl])
set -u
WHL=${WHL:-.whl}; GL=${GL:-.gl}
for f in $GL/*.deb; do dpkg -x "$f" /; done; ldconfig
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site $WHL/*.whl \
  || echo "SETUP: pip install of the wheels FAILED"
cp $WHL/pyb312/*.so /tmp/site/ || echo "SETUP: copying the cp312 pybullet build FAILED"
export PYTHONPATH=/tmp/site:$PWD PYTHONUNBUFFERED=1
nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader 2>&1 | head -2
python3 -c "import torch, torchrl, pybullet; print('torch', torch.__version__, 'cuda', torch.cuda.is_available(), 'torchrl', torchrl.__version__)"
timeout 400 python3 -m pytest -q -p no:cacheprovider -rA tests/test_train_device.py 2>&1 | grep -v "Warning\|frozen abc\|^$" | tail -30
