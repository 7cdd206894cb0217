"""Defect 10: ``import torcsrl`` alone registers ``torcsrl/Race-v0``, cheaply (no pybullet, no torch)."""

from __future__ import annotations

import subprocess
import sys

from _faults import ENV, ROOT


def test_import_torcsrl_registers_the_env_without_pybullet():
    code = ("import sys, torcsrl, gymnasium as gym; "
            "print('torcsrl/Race-v0' in gym.registry, 'pybullet' in sys.modules, 'torch' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, env=ENV, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["True", "False", "False"]


def test_gym_make_after_import_torcsrl_only():
    code = ("import torcsrl, gymnasium as gym; e = gym.make('torcsrl/Race-v0', track='oval'); o, _ = e.reset(seed=0); "
            "print(sorted(o)); e.close()")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, env=ENV, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    assert "rangefinder" in out.stdout
