"""Batched episodes (torcsrl.evaluate.batched): the cells of one policy and track driven as cars of one env give
the one-car path's episodes, bit for bit, and the report's batched path writes the same cells. (The exact relation:
bit-equal while no two cars touch the ground with their chassis in the same substep; these short episodes never do.
benchmarks/report_throughput.py counts the episodes of a full grid where that happened.)"""

from __future__ import annotations

import json
import math

import pytest
import torch
from tensordict import TensorDict

from torcsrl.envs import make_env
from torcsrl.evaluate import run_cell
from torcsrl.evaluate.batched import EnsembleRowActor, RowActor, row_actor, run_batch, supports_batch
from torcsrl.policies import REFERENCE_CAMERA_POLICY, EnsemblePolicy, load_policy
from torcsrl.report import ReportConfig, run_report


@pytest.fixture(autouse=True)
def _one_thread():
    torch.set_num_threads(1)


def _same(a, b) -> bool:
    return a == b or (isinstance(a, float) and isinstance(b, float) and math.isnan(a) and math.isnan(b))


def _diff(rows_a, rows_b) -> list:
    out = []
    for ra, rb in zip(rows_a, rows_b, strict=True):
        out += [(ra["corruption"], ra["severity"], ra["episode"], k, ra[k], rb[k]) for k in ra if not _same(ra[k], rb[k])]
    return out


def test_row_actor_equals_the_one_car_policy_row_for_row():
    pol = load_policy("reference")
    assert supports_batch(pol) and not supports_batch(load_policy("heuristic")) and not supports_batch(load_policy("random"))
    g = torch.Generator().manual_seed(0)
    obs = {k: torch.rand(37, *s, generator=g) * 100 for k, s in pol.obs_shapes.items()}
    rows = RowActor(pol)(obs)
    one = torch.stack([pol._act(*(obs[k][i] for k in pol.obs_keys)) for i in range(37)])  # one car: 1-D observations
    assert torch.equal(rows, one)
    # a plain batched forward is NOT bit-equal (other kernels): the reason RowActor exists
    assert not torch.equal(pol._act(*(obs[k] for k in pol.obs_keys)), one)


def test_row_actor_keeps_each_rows_history_and_grip_estimate_as_the_one_car_policy():
    """The shipped racer keeps 3 s of its state (state_history=30), estimates the grip from it and drives on the newest
    1 s: a batch of 5 rows, two of which restart mid-way, gives each row the actions of its own one-car policy."""
    pol = load_policy("reference_racer").inner.members[0]  # the shipped racer: a medoid of four such students, guarded
    assert pol.state_history > 1 and pol.actor.grip_head is not None and pol.actor._selects and supports_batch(pol)
    g = torch.Generator().manual_seed(0)
    batch, ones = RowActor(pol), [load_policy("reference_racer").inner.members[0] for _ in range(5)]
    for t in range(8):
        obs = {k: torch.rand(5, *s, generator=g) * 60 for k, s in pol.obs_shapes.items()}
        if t == 5:  # rows 1 and 3 start new episodes
            batch.forget([1, 3])
            ones[1].reset()
            ones[3].reset()
        rows = batch(obs)
        one = torch.stack([p._act(*(obs[k][i] for k in p.obs_keys)) for i, p in enumerate(ones)])
        assert torch.equal(rows, one), t
    # the history matters: a row that forgets its readings acts otherwise on the same observation
    obs = {k: torch.rand(5, *s, generator=g) * 60 for k, s in pol.obs_shapes.items()}
    before = batch(obs)
    batch.forget([0])
    assert not torch.equal(batch(obs)[0], before[0])


def test_row_actor_drives_ppos_mean_action_as_the_one_car_policy():
    """The shipped PPO driver (``reference_rl``: a tanh-Gaussian actor with a grip head on a 30-reading state history)
    batches too: its mean action is the same MLP + tanh, row for row the one-car policy's, across a row's restart."""
    pol = load_policy("reference_rl")
    assert type(pol.actor).__name__ == "TanhGaussianActor" and pol.state_history == 30 and supports_batch(pol)
    g = torch.Generator().manual_seed(1)
    batch, ones = RowActor(pol), [load_policy("reference_rl") for _ in range(4)]
    for t in range(6):
        obs = {k: torch.rand(4, *s, generator=g) * 60 for k, s in pol.obs_shapes.items()}
        if t == 3:
            batch.forget([2])
            ones[2].reset()
        one = torch.stack([p._act(*(obs[k][i] for k in p.obs_keys)) for i, p in enumerate(ones)])
        assert torch.equal(batch(obs), one), t


def test_a_stateful_racer_drives_batched_cells_as_one_car_at_a_time():
    """A student of reference_racer (history + grip head) in groups of 2 cars that restart for the next cell: the
    one-car rows."""
    pol = load_policy("reference_racer").inner.members[0]
    degs = [None, "state.noise@3", "rangefinder.dropout@2"]
    kw = dict(episodes=2, laps=1, seed=5, max_steps=60, env_kwargs={"start": "random"})
    batched = run_batch(pol, "rallycross", None, degs, max_cars=2, **kw)
    for d, rows_b in zip(degs, batched):
        rows_a, _ = run_cell(pol, "rallycross", None, d, **kw)
        assert _diff(rows_a, rows_b) == [], d
    assert batched[1][0]["return"] != batched[0][0]["return"]


def test_the_shipped_racer_an_ensemble_drives_batched_cells_as_one_car_at_a_time():
    """reference_racer is a medoid ensemble of four stateful students behind a side guard: each member batched row for
    row, combined per row, the guard per row."""
    from torcsrl.evaluate.batched import GuardRowActor

    pol = load_policy("reference_racer")
    assert isinstance(pol.inner, EnsemblePolicy) and supports_batch(pol) and isinstance(row_actor(pol), GuardRowActor)
    assert isinstance(row_actor(pol).inner, EnsembleRowActor)
    degs = [None, "state.noise@3"]
    kw = dict(episodes=2, laps=1, seed=5, max_steps=50, env_kwargs={"start": "random"})
    batched = run_batch(pol, "rallycross", None, degs, max_cars=2, **kw)
    for d, rows_b in zip(degs, batched):
        rows_a, _ = run_cell(pol, "rallycross", None, d, **kw)
        assert _diff(rows_a, rows_b) == [], d
    assert not supports_batch(load_policy(f"{REFERENCE_CAMERA_POLICY}"))  # pixels: one car at a time


def _racer_rows(n: int) -> dict[str, torch.Tensor]:
    """``n`` rows of one real observation of the shipped racer (4 s into a lap of the oval alone), every opponents
    sector free (200 m)."""
    racer = load_policy("reference_racer")
    env = make_env(track="oval", sensors=racer.env_overrides["sensors"], control_hz=10, substeps=20)
    try:
        td = env.reset()
        for _ in range(40):
            td = env.step(racer(td))["next"]
    finally:
        env.close()
    obs = {k: td[k].expand(n, *td[k].shape).clone() for k in racer.obs_keys}
    obs["opponents"][:] = 200.0
    return obs


def test_a_guarded_ensemble_guards_each_row_by_its_own_opponents_as_the_one_car_ensemble(tmp_path):
    """``@guarded``: each row's pedal is the most cautious member's only where that row sees a car close ahead."""
    from torcsrl.policies import REFERENCE_RACER_POLICY, export_member

    spec = "+".join(str(export_member(REFERENCE_RACER_POLICY, i, tmp_path / f"m{i}.pt")) for i in range(4)) + "@guarded:30"
    pol = load_policy(spec)
    obs = _racer_rows(6)  # each row with its own opponents
    obs["opponents"][3:, 18] = torch.tensor([12.0, 16.0, 45.0])  # rows 3-4: a car close ahead; row 5: 45 m ahead
    rows = row_actor(pol)(obs)
    one = torch.stack([load_policy(spec)(TensorDict({k: v[i] for k, v in obs.items()}, []))["action"] for i in range(6)])
    assert torch.equal(rows, one)
    assert pol.near_rows(obs).tolist() == [False, False, False, True, True, False]
    medoid = row_actor(load_policy(spec.replace("@guarded:30", "@medoid")))(obs)
    assert torch.equal(rows[[0, 1, 2, 5]], medoid[[0, 1, 2, 5]]) and not torch.equal(rows[3:5], medoid[3:5])


def test_a_side_guard_corrects_each_row_by_its_own_opponents_as_the_one_car_guard(tmp_path):
    """The shipped racer (its four students' medoid behind a side guard) and the same as a ``side_guard:`` spec:
    batched (the members row for row, then the guard row-wise), each row's steering is corrected only where that row
    sees a car beside it — what the one-car guard does, to the bit."""
    from torcsrl.evaluate.batched import GuardRowActor
    from torcsrl.policies import REFERENCE_RACER_POLICY, export_member

    medoid = "+".join(str(export_member(REFERENCE_RACER_POLICY, i, tmp_path / f"m{i}.pt")) for i in range(4)) + "@medoid"
    spec = f"side_guard:{medoid}"
    pol = load_policy(spec)
    assert supports_batch(pol) and isinstance(row_actor(pol), GuardRowActor)
    obs = _racer_rows(6)  # each row with its own opponents
    obs["opponents"][3, 9] = 2.0  # row 3: a car beside on the left; row 4: on the right; row 5: 12 m ahead
    obs["opponents"][4, 26] = 2.2
    obs["opponents"][5, 18] = 12.0
    rows = row_actor(pol)(obs)
    one = torch.stack([load_policy(spec)(TensorDict({k: v[i] for k, v in obs.items()}, []))["action"] for i in range(6)])
    assert torch.equal(rows, one)
    assert torch.equal(row_actor(load_policy("reference_racer"))(obs), rows)  # the shipped file: the same driver
    bare = row_actor(load_policy(medoid))(obs)
    assert torch.equal(rows[[0, 1, 2, 5]], bare[[0, 1, 2, 5]])  # nobody beside: the medoid's own action
    assert rows[3, 0] < bare[3, 0] and rows[4, 0] > bare[4, 0] and torch.equal(rows[3:5, 1], bare[3:5, 1])


@pytest.mark.parametrize("start,max_cars", [("grid", None), ("random", None), ("random", 4)])
def test_batched_cells_equal_the_one_car_path(start, max_cars):
    """Clean, step noise, episode faults, a temporal fault and a weather preset; 2 episodes each: 12 cars at once, or
    4 cars whose groups of 2 are reset to drive the next cell when theirs has ended (continuous batching)."""
    pol = load_policy("reference")
    degs = [None, "rangefinder.fog@3", "weather.rain@4", "state.latency@2", "rangefinder.stuck@5", "rangefinder.bias_scale@2"]
    kw = dict(episodes=2, laps=1, seed=3, max_steps=150, env_kwargs={"start": start})
    batched = run_batch(pol, "rallycross", None, degs, max_cars=max_cars, **kw)
    assert [len(r) for r in batched] == [2] * len(degs)
    for d, rows_b in zip(degs, batched):
        rows_a, _ = run_cell(pol, "rallycross", None, d, **kw)
        assert _diff(rows_a, rows_b) == [], d
    # the grid is not trivial: the weather changed the driving, and random starts differ per episode
    ret = [[r["return"] for r in rows] for rows in batched]
    assert ret[1] != ret[0] and ret[2] != ret[0]
    if start == "random":
        assert ret[0][0] != ret[0][1]


def test_batched_report_writes_the_same_cells_as_one_car_at_a_time(tmp_path):
    cfg = dict(policies=["reference"], tracks=["kidney"], degradations=["rangefinder.dropout", "state.noise"], severities=[0, 3],
               episodes=2, laps=1, max_steps=80, random_max_steps=30, workers=1, n_boot=50)
    one = run_report(ReportConfig(**cfg, batch_cars=1), tmp_path / "one", verbose=False)
    many = run_report(ReportConfig(**cfg, batch_cars=64), tmp_path / "many", verbose=False)
    assert one["computed"] == many["computed"] == 4  # clean, 2 degradations, random

    def cells(d):
        rec = json.loads((d / "robustness.json").read_text())
        return {(c["cell"]["policy"], c["cell"]["corruption"], c["cell"]["severity"]): c["rows"] for c in rec["cells"]}

    a, b = cells(tmp_path / "one"), cells(tmp_path / "many")
    assert a.keys() == b.keys()
    for k in a:
        assert a[k] == b[k], k
    assert many["summary"]["policies"]["reference"]["mrr"] == one["summary"]["policies"]["reference"]["mrr"]
