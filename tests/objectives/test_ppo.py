"""PPO on tensors (torcsrl.objectives.ppo, torcsrl.agents.ppo): the same numbers as TorchRL's ClipPPOLoss and
ProbabilisticActor on the same batch and draws — every output term, the gradients of both networks, the collected
actions and log-probabilities, one whole update step — and gradient isolation of its two losses."""

from types import SimpleNamespace

import pytest
import torch
from omegaconf import OmegaConf
from tensordict import TensorDict
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.modules import ValueOperator
from torchrl.objectives import ClipPPOLoss as TorchRLClipPPOLoss
from torchrl.objectives import ValueEstimators

from torcsrl import agents
from torcsrl.agents import _build
from torcsrl.agents.ppo import PPOPolicy
from torcsrl.envs.toy import make_toy_env
from torcsrl.nets import ObsEncoder, TanhGaussianActor, ValueNet
from torcsrl.objectives.ppo import ClipPPOLoss, probabilistic_actor

CFG = OmegaConf.merge(OmegaConf.load("conf/algo/base.yaml"), {k: v for k, v in OmegaConf.load("conf/algo/ppo.yaml").items() if k != "defaults"},
                      {"actor_hidden": [16, 16], "critic_hidden": [16, 16], "encoder": {"cnn_channels": [4], "feature_dim": 8}})
TOL = dict(rtol=1e-6, atol=1e-7)  # the two compute the same operations in the same order: equal in practice


def _setup(pixels: bool, bounds: tuple[float, float] | None, entropy_coef: float, n: int = 48) -> SimpleNamespace:
    """keys, low, high, our loss ``mine``, TorchRL's ``ref`` over the same networks, a batch ``data`` collected by
    TorchRL's policy with advantages and value targets, ``actor``, ``critic``; ``bounds``: None = the env's [-1, 1],
    else the first action dimension's bounds (the second: [-1, 0.5])."""
    keys = ["rangefinder", "state", "pixels"] if pixels else ["rangefinder", "state"]
    env = make_toy_env(sensors=keys, camera={"height": 16, "width": 16} if pixels else None, seed=0)
    low, high = _build.action_bounds(env) if bounds is None else (torch.tensor([bounds[0], -1.0]), torch.tensor([bounds[1], 0.5]))
    enc = lambda: ObsEncoder(env.observation_spec, keys, cnn_channels=(4,), feature_dim=8, obs_norm=True)  # noqa: E731
    actor = TanhGaussianActor(enc(), low, high, (16, 16), state_dependent_std=False, log_std_init=-0.5)
    critic = ValueNet(enc(), (16, 16))
    kw = dict(clip_epsilon=0.2, entropy_coeff=entropy_coef, critic_coeff=0.5)
    mine = ClipPPOLoss(actor, critic, obs_keys=keys, action_low=low, action_high=high, **kw)
    ref = TorchRLClipPPOLoss(probabilistic_actor(actor, keys, low, high), ValueOperator(critic, in_keys=keys), loss_critic_type="l2",
                             normalize_advantage=True, **kw)
    for m in (mine, ref):
        m.make_value_estimator(ValueEstimators.GAE, gamma=0.99, lmbda=0.95)
    td = env.reset()
    obs = {k: td[k].expand(n, *td[k].shape).clone() for k in keys}
    obs = {k: (v + 3 * torch.rand_like(v)) if v.is_floating_point() else torch.randint_like(v, 256) for k, v in obs.items()}
    for m in (actor, critic):  # statistics that are not the identity
        m.encoder.update_norm(*[obs[k] for k in keys])
    data = TensorDict(obs, [n])
    with torch.no_grad(), set_exploration_type(ExplorationType.RANDOM):
        probabilistic_actor(actor, keys, low, high)(data)
    data.set("advantage", torch.randn(n, 1) * 3 + 1)
    data.set("value_target", torch.randn(n, 1))
    with torch.no_grad():  # a policy that moved since collection: ratios away from 1, some clipped
        for p in actor.net.parameters():
            p.add_(0.3 * torch.randn_like(p))
        actor.log_std.add_(0.2)
    return SimpleNamespace(keys=keys, low=low, high=high, mine=mine, ref=ref, data=data, actor=actor, critic=critic)


def _run(loss, data, params, seed=7):
    torch.manual_seed(seed)  # the entropy estimate's draw
    for p in params:
        p.grad = None
    out = loss(data.clone())
    (out["loss_objective"] + out["loss_entropy"] + out["loss_critic"]).backward()
    return out, [p.grad.clone() for p in params]


@pytest.mark.parametrize("pixels", [False, True], ids=["vector", "pixels"])
@pytest.mark.parametrize("bounds", [None, (-2.0, 3.0)], ids=["unit-bounds", "other-bounds"])
@pytest.mark.parametrize("entropy_coef", [0.0, 0.01])
def test_terms_and_gradients_equal_torchrl_clip_ppo_loss(pixels, bounds, entropy_coef):
    torch.manual_seed(0)
    t = _setup(pixels, bounds, entropy_coef)
    params = [*t.actor.parameters(), *t.critic.parameters()]
    out_ref, g_ref = _run(t.ref, t.data, params)
    out, g = _run(t.mine, t.data, params)
    assert set(out_ref.keys()) <= set(out.keys())
    for k in out_ref.keys():
        torch.testing.assert_close(out[k], out_ref[k], **TOL, msg=k)
    assert 0 < float(out["clip_fraction"]) < 1 and abs(float(out["kl_approx"])) > 1e-3  # the clip and the ratio are exercised
    assert float(out["entropy"]) != 0 and (float(out["loss_entropy"].detach()) != 0) == (entropy_coef != 0)
    for p, a, b in zip(params, g, g_ref):
        torch.testing.assert_close(a, b, **TOL)
    # the entropy is TorchRL's one-draw estimate: another draw, another value; the deterministic terms stay
    torch.manual_seed(8)
    other = t.mine(t.data.clone())
    assert float(other["entropy"]) != float(out["entropy"])
    for k in ("loss_objective", "loss_critic", "kl_approx", "clip_fraction"):
        torch.testing.assert_close(other[k], out[k], rtol=0, atol=0)


def test_advantages_computed_when_missing_as_torchrl_does():
    torch.manual_seed(0)
    t = _setup(False, None, 0.0, n=16)
    data = t.data
    del data["advantage"], data["value_target"]
    nxt = {k: data[k] + 0.1 for k in t.keys}
    data.set("next", TensorDict({**nxt, "reward": torch.randn(16, 1), "done": torch.zeros(16, 1, dtype=torch.bool),
                                 "terminated": torch.zeros(16, 1, dtype=torch.bool)}, [16]))
    params = [*t.actor.parameters(), *t.critic.parameters()]
    out_ref, g_ref = _run(t.ref, data, params)
    out, g = _run(t.mine, data, params)
    for k in ("loss_objective", "loss_critic", "entropy", "kl_approx"):
        torch.testing.assert_close(out[k], out_ref[k], **TOL, msg=k)
    for a, b in zip(g, g_ref):
        torch.testing.assert_close(a, b, **TOL)


def test_each_loss_reaches_only_its_own_network():
    torch.manual_seed(0)
    t = _setup(True, None, 0.01)
    actor, critic = t.actor, t.critic
    batch = t.mine.batch(t.data)
    la, meta = t.mine.actor_loss(batch)
    la.backward()
    assert all(p.grad is None for p in critic.parameters())
    assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in actor.parameters())
    actor.zero_grad(set_to_none=True)
    lc, _ = t.mine.value_loss(batch)
    lc.backward()
    assert all(p.grad is None for p in actor.parameters())
    assert all(p.grad is not None for p in critic.parameters())
    assert {"loss_objective", "loss_entropy", "entropy", "kl_approx", "clip_fraction"} <= set(meta)
    assert all(not v.requires_grad for v in meta.values())


def test_minibatches_are_slices_of_one_shuffle():
    torch.manual_seed(0)
    t = _setup(True, None, 0.0)
    perm = torch.randperm(48)
    whole = t.mine.batch(t.data)[perm]
    for s in range(0, 48, 16):
        a, b = whole[s:s + 16], t.mine.batch(t.data[perm[s:s + 16]])
        for x, y in zip([*a.actor_in, *a.critic_in, a.preimage, a.log_det, a.log_prob, a.advantage, a.value_target],
                        [*b.actor_in, *b.critic_in, b.preimage, b.log_det, b.log_prob, b.advantage, b.value_target]):
            assert torch.equal(x, y)
    assert len(whole) == 48 and len(whole[:16]) == 16
    assert whole.actor_in[1] is whole.critic_in[1]  # the image rows are gathered once for both networks


@pytest.mark.parametrize("bounds", [None, (-2.0, 3.0)], ids=["unit-bounds", "other-bounds"])
def test_collection_policy_equals_torchrl_probabilistic_actor(bounds):
    torch.manual_seed(0)
    t = _setup(False, bounds, 0.0)
    obs = t.data.select(*t.keys)
    policy, trl = PPOPolicy(t.actor, t.keys, t.low, t.high), probabilistic_actor(t.actor, t.keys, t.low, t.high)
    for kind in (ExplorationType.RANDOM, ExplorationType.DETERMINISTIC):
        with set_exploration_type(kind), torch.no_grad():
            torch.manual_seed(3)
            a = policy.act(obs.clone())
            torch.manual_seed(3)
            b = trl(obs.clone())
        for k in ("action", "action_log_prob"):
            torch.testing.assert_close(a[k], b[k], rtol=0, atol=0, msg=f"{kind} {k}")
    assert "loc" not in a.keys()  # not written: nothing reads it


def test_update_step_equals_the_torchrl_update():
    """One ``agents.ppo.update`` (our loss, lean gradient clip, fused Adam) moves the networks exactly as the same step
    through TorchRL's ``ClipPPOLoss`` forward, ``clip_grad_norm_`` and the same optimisers."""
    cfg = OmegaConf.merge(CFG, {"entropy_coef": 0.01, "grad_clip": 0.05})
    states = []
    for path in ("torchrl", "ours"):
        torch.manual_seed(0)
        t = _setup(False, None, 0.01, n=32)
        loss = t.ref if path == "torchrl" else t.mine
        optim = agents.get("ppo").make_optimizers(cfg, loss)
        torch.manual_seed(5)
        for _ in range(2):
            if path == "ours":
                agents.get("ppo").update(cfg, t.mine, optim, None, t.mine.batch(t.data), 0)
            else:
                td = t.ref(t.data.clone())
                total = td["loss_critic"] + (td["loss_objective"] + td["loss_entropy"])
                for o in optim.values():
                    o.zero_grad(set_to_none=True)
                total.backward()
                torch.nn.utils.clip_grad_norm_([p for o in optim.values() for p in o.param_groups[0]["params"]], cfg.grad_clip)
                for o in optim.values():
                    _build._step(o)
        states.append([p.detach().clone() for p in [*t.actor.parameters(), *t.critic.parameters()]])
    for a, b in zip(*states):
        torch.testing.assert_close(a, b, **TOL)


def test_clip_grad_norm_equals_torch():
    torch.manual_seed(0)
    ps = [torch.randn(5, 3, requires_grad=True), torch.randn(7, requires_grad=True), torch.randn(2, 2, requires_grad=True)]
    qs = [p.detach().clone().requires_grad_() for p in ps]
    for max_norm in (0.1, 100.0):
        for group in (ps, qs):
            for p in group:
                p.grad = torch.arange(p.numel(), dtype=torch.float32).reshape(p.shape) * 0.3
        n1 = torch.nn.utils.clip_grad_norm_(ps, max_norm)
        n2 = _build.clip_grad_norm(qs, max_norm)
        assert torch.equal(n1, n2) and all(torch.equal(p.grad, q.grad) for p, q in zip(ps, qs))


def test_state_dict_keys_are_torchrl_s():
    """Checkpoints of the TorchRL-forward loss load into this one (the same modules, buffers and estimator)."""
    torch.manual_seed(0)
    t = _setup(False, None, 0.0)
    assert list(t.mine.state_dict()) == list(t.ref.state_dict())
    t.mine.load_state_dict(t.ref.state_dict())


def test_scheduled_coefficients_are_read():
    """``entropy_coeff`` and ``clip_epsilon`` are buffers a schedule may change in place; the tensor path follows."""
    torch.manual_seed(0)
    t = _setup(False, None, 0.0)
    params = [*t.actor.parameters(), *t.critic.parameters()]
    _run(t.mine, t.data, params)  # caches the coefficients as they were
    for m in (t.mine, t.ref):
        m.entropy_coeff.fill_(0.5)
        m.clip_epsilon.fill_(0.05)
    out_ref, g_ref = _run(t.ref, t.data, params)
    out, g = _run(t.mine, t.data, params)
    assert float(out["loss_entropy"].detach()) != 0
    for k in ("loss_objective", "loss_entropy", "clip_fraction"):
        torch.testing.assert_close(out[k], out_ref[k], **TOL, msg=k)
    for a, b in zip(g, g_ref):
        torch.testing.assert_close(a, b, **TOL)


def test_bfloat16_update_is_mixed_precision_and_close_to_float32():
    """algo.precision=bfloat16 (autocast around the losses): finite losses; weights, gradients and Adam's state stay
    float32; the policy that collected the batch scores it nearly as it did (float32: log-ratio ~1e-5; bfloat16: ~0.04
    here, the rounding of the bfloat16 hidden activations, against a clip range of 0.2); one step moves the weights as
    the float32 step does."""
    runs = {}
    for prec in ("float32", "bfloat16"):
        cfg = OmegaConf.merge(CFG, {"precision": prec})
        torch.manual_seed(0)
        t = _setup(False, None, 0.01, n=32)
        with torch.no_grad():  # the batch's log-probabilities are the current policy's (a fresh rollout)
            PPOPolicy(t.actor, t.keys, t.low, t.high)(t.data)
        batch = t.mine.batch(t.data)
        with torch.no_grad(), _build.precision_context(prec, "cpu"):
            _, meta = t.mine.actor_loss(batch)
        assert float(meta["_log_weight"].abs().max()) < (1e-4 if prec == "float32" else 0.1)
        params = [*t.actor.parameters(), *t.critic.parameters()]
        before = [p.detach().clone() for p in params]
        optim = agents.get("ppo").make_optimizers(cfg, t.mine)
        torch.manual_seed(5)
        out = agents.get("ppo").update(cfg, t.mine, optim, None, batch, 0)
        assert all(torch.isfinite(v) and v.dtype == torch.float32 for v in out.values())
        assert all(p.dtype == torch.float32 for p in params)
        assert all(s["exp_avg"].dtype == torch.float32 for o in optim.values() for s in o.state.values())
        runs[prec] = (float(out["loss/critic"]), torch.cat([(p.detach() - b).flatten() for p, b in zip(params, before)]))
    (l32, d32), (l16, d16) = runs["float32"], runs["bfloat16"]
    assert l16 == pytest.approx(l32, rel=0.05)
    assert torch.nn.functional.cosine_similarity(d32, d16, dim=0) > 0.9
