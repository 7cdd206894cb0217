"""Networks new with SAC and PPO: the tanh-Gaussian actor's density, the critics' detached pass, running statistics."""

import pytest
import torch

from torcsrl.envs.toy import make_toy_env
from torcsrl.nets import Critic, ObsEncoder, RunningNorm, TanhGaussianActor


def test_state_independent_std_starts_per_action_dimension():
    """``log_std_init``: one number for every action, or one per action (a quieter steer than pedal); a list of the
    wrong length is refused in one line."""
    env = make_toy_env()
    low, high = torch.full((2,), -1.0), torch.full((2,), 1.0)

    def actor(init):
        return TanhGaussianActor(ObsEncoder(env.observation_spec, ["rangefinder", "state"]), low, high, (8,),
                                 state_dependent_std=False, log_std_init=init)

    torch.testing.assert_close(actor(-0.5).log_std.data, torch.tensor([-0.5, -0.5]))
    a = actor([-1.0, 0.0])
    torch.testing.assert_close(a.log_std.data, torch.tensor([-1.0, 0.0]))
    _, std = a.dist(torch.rand(3, 19) * 50, torch.randn(3, 6))
    torch.testing.assert_close(std, torch.tensor([[0.3679, 1.0]]).expand(3, 2), rtol=1e-4, atol=1e-4)
    with pytest.raises(ValueError, match=r"one number, or one per action dimension \(2\)"):
        actor([0.0, 0.0, 0.0])


@pytest.mark.parametrize("bounds", [(-1.0, 1.0), (-2.0, 0.5)])
@pytest.mark.parametrize("state_dependent_std", [True, False])
def test_tanh_gaussian_log_prob_equals_torchrl_tanh_normal(bounds, state_dependent_std):
    from torchrl.modules import TanhNormal

    torch.manual_seed(0)
    env = make_toy_env()
    keys = ["rangefinder", "state"]
    low, high = torch.full((2,), bounds[0]), torch.full((2,), bounds[1])
    actor = TanhGaussianActor(ObsEncoder(env.observation_spec, keys), low, high, (16,), state_dependent_std=state_dependent_std)
    obs = [torch.rand(64, 19) * 50, torch.randn(64, 6)]
    a, logp, mean = actor.sample(*obs)
    loc, std = actor.dist(*obs)
    ref = TanhNormal(loc, std, low=low, high=high)
    torch.testing.assert_close(logp, ref.log_prob(a), rtol=1e-4, atol=1e-4)
    torch.testing.assert_close(mean, ref.deterministic_sample)
    torch.testing.assert_close(actor(*obs), mean)  # what evaluation drives
    assert ((a >= low) & (a <= high)).all()
    a.sum().backward()  # reparameterised: the draw carries gradients to the actor
    assert all(p.grad is not None for p in actor.net.parameters())


def test_critic_detached_equals_forward_and_has_no_param_grad():
    torch.manual_seed(0)
    env = make_toy_env()
    critic = Critic(ObsEncoder(env.observation_spec, ["rangefinder", "state"]), 2, (16, 16), num_nets=2)
    obs = [torch.rand(8, 19) * 50, torch.randn(8, 6)]
    action = torch.rand(8, 2, requires_grad=True)
    q = critic.detached(*obs, action)
    torch.testing.assert_close(q, critic(*obs, action))
    q.sum().backward()
    assert action.grad is not None and all(p.grad is None for p in critic.parameters())


def test_running_norm_merges_batches_like_one_pass_and_saves_its_statistics():
    torch.manual_seed(0)
    x = torch.randn(300, 5) * torch.tensor([1.0, 2, 3, 4, 5]) + 7
    norm = RunningNorm(5)
    for chunk in x.split([1, 99, 200]):
        norm.update(chunk)
    torch.testing.assert_close(norm.mean, x.double().mean(0))
    torch.testing.assert_close(norm.var, x.double().var(0, unbiased=False))
    y = norm(x)
    torch.testing.assert_close(y.mean(0), torch.zeros(5), atol=1e-5, rtol=0)
    other = RunningNorm(5)
    other.load_state_dict(norm.state_dict())
    torch.testing.assert_close(other(x), y)


def test_encoder_obs_norm_standardises_the_scaled_vectors():
    env = make_toy_env()
    keys = ["rangefinder", "state"]
    enc, plain = ObsEncoder(env.observation_spec, keys, obs_norm=True), ObsEncoder(env.observation_spec, keys)
    obs = [torch.rand(256, 19) * 50, torch.randn(256, 6)]
    torch.testing.assert_close(enc(*obs), plain(*obs))  # no statistics yet: the identity
    enc.update_norm(*obs)
    out = enc(*obs)
    torch.testing.assert_close(out.mean(0), torch.zeros(out.shape[-1]), atol=1e-4, rtol=0)
    assert "norm.mean" in enc.state_dict() and "norm.mean" not in plain.state_dict()


@pytest.mark.parametrize("keys", [["state"], ["rangefinder", "state"], ["rangefinder", "pixels"], ["pixels"]])
@pytest.mark.parametrize("obs_norm", [False, True])
def test_encoder_prepare_then_features_is_forward(keys, obs_norm):
    """What PPO prepares once per rollout and finishes per minibatch is the encoder's forward, to the bit."""
    torch.manual_seed(0)
    env = make_toy_env(sensors=keys, camera={"height": 16, "width": 16} if "pixels" in keys else None)
    enc = ObsEncoder(env.observation_spec, keys, cnn_channels=(4,), feature_dim=8, obs_norm=obs_norm)
    td = env.reset()
    obs = [td[k].expand(32, *td[k].shape).clone() for k in keys]
    obs = [o + torch.rand_like(o) if o.is_floating_point() else torch.randint_like(o, 256) for o in obs]
    enc.update_norm(*obs)
    prepared = enc.prepare(*obs)
    assert torch.equal(enc.features(*prepared), enc(*obs))
    assert torch.equal(enc.features(*[p[5:9] for p in prepared]), enc(*[o[5:9] for o in obs]))  # rows prepared in bulk


def test_mlp_forward_is_the_module_call():
    from torcsrl.nets import ValueNet, mlp, mlp_forward

    torch.manual_seed(0)
    net, x = mlp(7, (16, 16), 3), torch.randn(5, 7)
    y1, y2 = net(x), mlp_forward(net, x)
    assert torch.equal(y1, y2)
    g1 = torch.autograd.grad(y1.sum(), list(net.parameters()))
    g2 = torch.autograd.grad(mlp_forward(net, x).sum(), list(net.parameters()))
    assert all(torch.equal(a, b) for a, b in zip(g1, g2))
    v = ValueNet(ObsEncoder(make_toy_env().observation_spec, ["state"]), (16,))
    assert torch.equal(v(torch.ones(2, 6)), v.net(v.encoder(torch.ones(2, 6))))


def test_an_image_too_small_for_the_conv_stack_is_one_line():
    env = make_toy_env(sensors=("pixels",), camera={"height": 32, "width": 48})
    ObsEncoder(env.observation_spec, ["pixels"], cnn_channels=(8, 8), cnn_kernels=(8, 4), cnn_strides=(4, 2))  # 32x48 fits
    with pytest.raises(ValueError) as e:  # the Nature-DQN stack needs 36 rows: 32 -> 7 -> 2 rows for a 3x3 kernel
        ObsEncoder(env.observation_spec, ["pixels"], cnn_channels=(16, 32, 32), cnn_kernels=(8, 4, 3), cnn_strides=(4, 2, 1))
    msg = str(e.value)
    assert "\n" not in msg and "32x48 (HxW) image is too small" in msg and "layer 2 gets 2x4 for a 3x3 kernel" in msg
