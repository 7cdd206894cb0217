"""Networks (fused ensemble == separate nets, encoders) and exploration modules."""

import math

import pytest
import torch
from tensordict import TensorDict
from torchrl.envs.utils import ExplorationType, set_exploration_type

from torcsrl.agents.exploration import ActionNoise, ParamNoiseActor, StochasticBrake
from torcsrl.nets import Critic, DeterministicActor, EnsembleLinear, ObsEncoder, random_shift
from torcsrl.envs.toy import make_toy_env


def test_ensemble_linear_equals_separate_linears():
    torch.manual_seed(0)
    lin = EnsembleLinear(2, 5, 3)
    x = torch.randn(7, 5)
    y = lin(x)
    for e in range(2):
        torch.testing.assert_close(y[e], x @ lin.weight[e] + lin.bias[e])
    x3 = torch.randn(2, 7, 5)
    y3 = lin(x3)
    for e in range(2):
        torch.testing.assert_close(y3[e], x3[e] @ lin.weight[e] + lin.bias[e])


@pytest.mark.parametrize("needs", [(True, True, True), (False, True, True), (True, False, False)])
def test_ensemble_scalar_head_values_and_gradients_equal_baddbmm(needs):
    """The one-column output layer (the twin critics' Q head) takes its own kernel: same maths as baddbmm."""
    torch.manual_seed(0)
    x, w, b = torch.randn(2, 9, 6, dtype=torch.float64), torch.randn(2, 6, 1, dtype=torch.float64), torch.randn(2, 1, 1, dtype=torch.float64)
    for t, n in zip((x, w, b), needs):
        t.requires_grad_(n)
    lin = EnsembleLinear(2, 6, 1).double()
    with torch.no_grad():
        lin.weight.copy_(w)
        lin.bias.copy_(b)
    torch.testing.assert_close(lin(x.detach()), torch.baddbmm(b, x, w).detach())
    from torcsrl.nets import ensemble_linear

    torch.autograd.gradcheck(ensemble_linear, (x, w, b))
    g = torch.randn(2, 9, 1, dtype=torch.float64)
    got = torch.autograd.grad(ensemble_linear(x, w, b), [t for t in (x, w, b) if t.requires_grad], g)
    want = torch.autograd.grad(torch.baddbmm(b, x, w), [t for t in (x, w, b) if t.requires_grad], g)
    for u, v in zip(got, want):
        torch.testing.assert_close(u, v)


def test_critic_member_matches_forward_and_has_no_param_grad():
    env = make_toy_env()
    keys = ["rangefinder", "state"]
    critic = Critic(ObsEncoder(env.observation_spec, keys), 2, (16, 16), num_nets=2)
    rf, st, a = torch.rand(4, 19) * 50, torch.zeros(4, 6), torch.rand(4, 2, requires_grad=True)
    full = critic(rf, st, a)
    m0 = critic.member(rf, st, a, index=0)
    torch.testing.assert_close(full[0], m0)
    m0.sum().backward()
    assert a.grad is not None and a.grad.abs().sum() > 0
    assert all(p.grad is None for p in critic.parameters())


def test_encoder_scales_vectors_from_spec_bounds_and_takes_pixels():
    env = make_toy_env(sensors=("rangefinder", "state", "pixels"), camera={"height": 32, "width": 32})
    enc = ObsEncoder(env.observation_spec, ["rangefinder", "state", "pixels"], cnn_channels=(4, 4), feature_dim=8)
    td = env.reset()
    out = enc(td["rangefinder"][None], td["state"][None], td["pixels"][None])
    assert out.shape == (1, 19 + 6 + 8)
    # rangefinder bounds [-1, 200] map to [-1, 1]
    assert out[0, :19].abs().max() <= 1.0 + 1e-6


def test_encoder_rejects_unknown_key():
    env = make_toy_env()
    with pytest.raises(ValueError, match="not in the env's observation spec"):
        ObsEncoder(env.observation_spec, ["lidar"])


def test_random_shift_keeps_dtype_and_shape_and_moves_content():
    g = torch.Generator().manual_seed(0)
    img = torch.arange(2 * 3 * 8 * 8, dtype=torch.float32).reshape(2, 3, 8, 8).to(torch.uint8)
    out = random_shift(img, 2, generator=g)
    assert out.dtype == torch.uint8 and out.shape == img.shape
    assert not torch.equal(out, img)
    assert torch.equal(random_shift(img, 0), img)


def _noise_td(n=1000):
    return TensorDict({"action": torch.zeros(n, 2), "is_init": torch.zeros(n, 1, dtype=torch.bool)}, [n])


def test_ou_noise_per_dim_mean_and_determinism():
    torch.manual_seed(0)
    lo, hi = -torch.ones(2), torch.ones(2)
    ou = ActionNoise("ou", lo, hi, sigma=[0.3, 0.3], theta=[0.6, 1.0], mu=[0.0, 0.5])
    td = _noise_td()
    for _ in range(30):
        td.set("action", torch.zeros(1000, 2))
        ou(td)
    a = td["action"]
    assert abs(float(a[:, 0].mean())) < 0.05  # steer OU mean 0
    assert abs(float(a[:, 1].mean()) - 0.5) < 0.05  # throttle OU mean 0.5
    # stationary std of x <- 0.4 x + 0.3 eps is 0.3 / sqrt(1 - 0.16)
    assert abs(float(a[:, 0].std()) - 0.3 / math.sqrt(0.84)) < 0.03
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        td2 = ou(_noise_td(4))
    assert torch.equal(td2["action"], torch.zeros(4, 2))


def test_gaussian_noise_is_clipped():
    torch.manual_seed(0)
    g = ActionNoise("gaussian", -torch.ones(2) * 10, torch.ones(2) * 10, sigma=1.0, clip=0.5)
    td = g(TensorDict({"action": torch.zeros(5000, 2)}, [5000]))
    assert float(td["action"].abs().max()) <= 0.5 + 1e-6
    assert float(td["action"].abs().max()) > 0.49


def test_stochastic_brake_rate():
    torch.manual_seed(0)
    b = StochasticBrake(prob=0.2, mu=0.3, sigma=0.0)
    td = b(TensorDict({"action": torch.full((10000, 2), 0.7)}, [10000]))
    braked = td["action"][:, 1] < 0
    assert abs(float(braked.float().mean()) - 0.2) < 0.02
    assert torch.allclose(td["action"][braked, 1], torch.tensor(-0.3))
    assert torch.all(td["action"][:, 0] == 0.7)


def test_param_noise_perturbs_and_adapts():
    torch.manual_seed(0)
    env = make_toy_env()
    actor = DeterministicActor(ObsEncoder(env.observation_spec, ["rangefinder", "state"]), -torch.ones(2), torch.ones(2), (16,))
    pn = ParamNoiseActor(actor, ["rangefinder", "state"], sigma=0.5, target_distance=1e-3, resample_frames=5)
    td = TensorDict({"rangefinder": torch.rand(8, 19) * 50, "state": torch.zeros(8, 6)}, [8])
    clean = actor(td["rangefinder"], td["state"])
    out = pn(td.clone())["action"]
    assert not torch.allclose(out, clean)
    s0 = float(pn.sigma)
    pn(td.clone())
    assert float(pn.sigma) < s0  # distance above target -> sigma shrinks
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        torch.testing.assert_close(pn(td.clone())["action"], clean)


def test_behaviour_policy_act_equals_its_tensordict_call():
    from omegaconf import OmegaConf

    from torcsrl import agents

    env = make_toy_env()
    keys = ["rangefinder", "state"]
    cfg = OmegaConf.merge(OmegaConf.load("conf/algo/base.yaml"), {"name": "x", "actor_hidden": [16], "exploration": {"kind": "ou"},
                                                                  "stochastic_brake": {"enabled": True, "prob": 0.5}})
    ag = agents.get("td3")
    policy = ag.make_exploration(cfg, ag.make_actor(cfg, env, keys), env, keys)
    td = TensorDict({"rangefinder": torch.rand(4, 19) * 50, "state": torch.zeros(4, 6), "is_init": torch.zeros(4, 1, dtype=torch.bool)}, [4])
    torch.manual_seed(0)
    slow = policy(td.clone())
    torch.manual_seed(0)
    fast = policy.act(td.clone())
    torch.testing.assert_close(fast["action"], slow["action"])
    torch.testing.assert_close(fast["_ou_noise"], slow["_ou_noise"])


def test_fused_adam_equals_torch_fused_adam_bit_for_bit():
    from torcsrl.agents._build import FusedAdam

    torch.manual_seed(0)
    a = torch.nn.Sequential(torch.nn.Linear(4, 16), torch.nn.ReLU(), torch.nn.Linear(16, 2))
    b = torch.nn.Sequential(torch.nn.Linear(4, 16), torch.nn.ReLU(), torch.nn.Linear(16, 2))
    b.load_state_dict(a.state_dict())
    oa = torch.optim.Adam(a.parameters(), lr=1e-3, weight_decay=0.01, fused=True)
    ob = FusedAdam(b.parameters(), lr=1e-3, weight_decay=0.01)
    for i in range(12):
        x = torch.randn(8, 4)
        for m, o in ((a, oa), (b, ob)):
            o.zero_grad(set_to_none=True)
            m(x).pow(2).mean().backward()
            o.step()
        if i == 5:  # a checkpoint round trip in the middle
            ob.load_state_dict(ob.state_dict())
    assert all(torch.equal(p, q) for p, q in zip(a.parameters(), b.parameters()))
    sa, sb = oa.state_dict()["state"], ob.state_dict()["state"]
    assert all(torch.equal(sa[k][n], sb[k][n]) for k in sa for n in sa[k])


def test_random_shift_equals_a_crop_of_the_replicate_padded_frame_at_the_drawn_offset():
    """The gather implementation against the plain definition: pad (replicate), crop H x W at the offset drawn."""
    img = torch.randint(0, 256, (5, 3, 7, 11), dtype=torch.uint8)
    out = random_shift(img, 3, generator=torch.Generator().manual_seed(4))
    off = torch.randint(0, 7, (5, 2), generator=torch.Generator().manual_seed(4))
    padded = torch.nn.functional.pad(img.float(), (3, 3, 3, 3), mode="replicate")
    for i in range(5):
        r, c = off[i].tolist()
        assert torch.equal(out[i], padded[i, :, r:r + 7, c:c + 11].to(torch.uint8))


def test_random_shift_per_axis_pads_shift_each_axis_by_its_own_range():
    """augment_shift=[rows, cols]: [4, 0] moves frames vertically only (a steering label stays true), [1, 3] each axis
    within its own range; shift_pad refuses what is not a pad in one line."""
    from torcsrl.nets import shift_pad

    img = torch.randint(0, 256, (64, 3, 9, 13), dtype=torch.uint8)
    padded = torch.nn.functional.pad(img.float(), (0, 0, 4, 4), mode="replicate")
    out = random_shift(img, shift_pad([4, 0]), generator=torch.Generator().manual_seed(1))
    rows = []
    for i in range(64):  # every output frame is a vertical crop of its padded frame, columns in place
        hit = [r for r in range(9) if torch.equal(out[i], padded[i, :, r:r + 9].to(torch.uint8))]
        assert hit
        rows.append(hit[0])
    assert len(set(rows)) > 4  # offsets are drawn
    padded = torch.nn.functional.pad(img.float(), (3, 3, 1, 1), mode="replicate")
    out = random_shift(img, (1, 3), generator=torch.Generator().manual_seed(2))
    offs = set()
    for i in range(64):
        hit = [(r, c) for r in range(3) for c in range(7) if torch.equal(out[i], padded[i, :, r:r + 9, c:c + 13].to(torch.uint8))]
        assert hit
        offs |= {hit[0]}
    assert {r for r, _ in offs} <= {0, 1, 2} and len({c for _, c in offs}) > 4
    assert shift_pad(4) == (4, 4) and shift_pad([4, 0]) == (4, 0) and shift_pad([2]) == (2, 2)
    for bad in (-1, [1, 2, 3], "x", 1.5):
        with pytest.raises(ValueError, match="expected a pad in pixels"):
            shift_pad(bad)
