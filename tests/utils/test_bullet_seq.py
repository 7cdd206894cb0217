"""torcsrl.utils.bullet (pybullet without its build banner) and torcsrl.utils.seq.as_list."""

from __future__ import annotations

import os
import subprocess
import sys

from omegaconf import OmegaConf

from torcsrl.utils.bullet import silenced_fds
from torcsrl.utils.seq import as_list


def test_the_first_pybullet_import_prints_nothing():
    code = "from torcsrl.utils.bullet import pybullet as p; c = p.connect(p.DIRECT); p.disconnect(c)"
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    assert r.stdout == "" and r.stderr == ""


def test_silenced_fds_hides_c_level_writes_and_restores_the_descriptors(capfd):
    print("before", flush=True)
    with silenced_fds():
        os.write(1, b"hidden out\n")
        os.write(2, b"hidden err\n")
    print("after", flush=True)
    os.write(2, b"err after\n")
    out, err = capfd.readouterr()
    assert out == "before\nafter\n" and err == "err after\n"


def test_as_list_one_value_or_many():
    assert as_list("kidney") == ["kidney"]
    assert as_list(["a", "b"]) == ["a", "b"] and as_list(("a", "b")) == ["a", "b"]
    assert as_list(OmegaConf.create(["a", "b"])) == ["a", "b"]
    assert as_list(3) == [3]
    assert as_list(None) == [None] and as_list(None, keep_none=True) is None
    assert as_list(("state", "pos"), atoms=(str, tuple)) == [("state", "pos")]
    assert as_list([("state", "pos"), "x"], atoms=(str, tuple)) == [("state", "pos"), "x"]
