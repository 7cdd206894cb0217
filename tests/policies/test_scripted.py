"""torcsrl.policies.scripted: the expert driven from observations."""

from __future__ import annotations

import pytest

from torcsrl.policies import PolicyError, load_policy


def test_centre_line_expert_drives_and_an_unknown_line_fails_in_one_line():
    from torcsrl.evaluate import run_cell
    from torcsrl.policies import ExpertPolicy

    rows, _ = run_cell(load_policy("expert_centre"), "hairpins", "asphalt", laps=1, env_kwargs={"control_hz": 10, "substeps": 20})
    assert rows[0]["success"]
    with pytest.raises(PolicyError, match=r"line='inside'; allowed: racing, centre"):
        ExpertPolicy(line="inside")
