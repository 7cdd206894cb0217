"""benchmarks/learning.py: the harness trains in chunks, validates after each and reports the milestones."""

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def test_learning_harness_runs_chunks_and_prints_its_table(tmp_path):
    out = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "learning.py"), "--env", "toy", "--algo", "td3", "--seeds", "0",
                          "--budget", "400", "--chunk", "200", "--eval-max-steps", "50", "--out", str(tmp_path), "--",
                          "debug=smoke", "threads=1"], capture_output=True, text=True, timeout=300, cwd=ROOT)
    assert out.returncode == 0, out.stderr[-2000:]
    chunks = [line for line in out.stdout.splitlines() if line.startswith("[learning] td3 seed 0:")]
    assert [c.split()[4] for c in chunks] == ["200", "400"]  # one validation per chunk, resumed from the previous chunk
    assert "first clean lap" in out.stdout and (tmp_path / "td3_toy_seed0" / "checkpoints").is_dir()
