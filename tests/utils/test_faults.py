"""torcsrl.utils.faults.cli_error: what every entry point prints and returns for an error."""

from __future__ import annotations

import errno
import signal

from torcsrl.utils.faults import Interrupted, cli_error


def test_cli_error_one_line_and_exit_code(capsys):
    assert cli_error("torcsrl.x", ValueError("laps must be >= 1, got 0")) == 2
    assert capsys.readouterr().err == "torcsrl.x: error: laps must be >= 1, got 0\n"
    full = OSError(errno.ENOSPC, "No space left on device", "/tmp/out/report.md")
    assert cli_error("torcsrl.x", full) == 2
    err = capsys.readouterr().err
    assert err.startswith("torcsrl.x: error: cannot write /tmp/out/report.md: No space left on device") and err.count("\n") == 1
    assert cli_error("torcsrl.x", Interrupted(signal.SIGTERM), stopped="workers stopped") == 128 + signal.SIGTERM
    assert capsys.readouterr().err == "torcsrl.x: error: stopped by SIGTERM; workers stopped\n"
    assert cli_error("torcsrl.x", KeyboardInterrupt()) == 130
    assert capsys.readouterr().err == "torcsrl.x: error: stopped by SIGINT\n"
