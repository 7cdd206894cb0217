"""Loss modules: gradient isolation, equality with TorchRL's DDPGLoss, TD3 target, C51 projection."""

import pytest
import torch
from omegaconf import OmegaConf
from tensordict import TensorDict
from torch import nn

from torcsrl import agents
from torcsrl.envs.toy import make_toy_env
from torcsrl.objectives.d4pg import categorical_projection

ALGO_CFG = OmegaConf.merge(
    OmegaConf.load("conf/algo/base.yaml"),
    {"name": "x", "actor_hidden": [16, 16], "critic_hidden": [16, 16], "encoder": {"cnn_channels": [4], "feature_dim": 8, "augment_shift": 2},
     "policy_noise": 0.2, "v_min": -10.0, "v_max": 10.0},
)


def _batch(env, keys, n=8):
    td = env.reset()
    obs = {k: td[k].expand(n, *td[k].shape).clone() for k in keys}
    for k in keys:
        if obs[k].is_floating_point():
            obs[k] = obs[k] + torch.rand_like(obs[k])
    nxt = {k: v.clone() for k, v in obs.items()}
    nxt.update(reward=torch.randn(n, 1), done=torch.zeros(n, 1, dtype=torch.bool), terminated=torch.zeros(n, 1, dtype=torch.bool))
    return TensorDict({**obs, "action": torch.rand(n, 2) * 2 - 1, "next": nxt}, [n])


@pytest.mark.parametrize("algo", agents.OFF_POLICY)
def test_gradients_reach_only_their_own_networks(algo):
    torch.manual_seed(0)
    keys = ["rangefinder", "state", "pixels"]
    env = make_toy_env(sensors=keys, camera={"height": 16, "width": 16})
    ag = agents.get(algo)
    actor = ag.make_actor(ALGO_CFG, env, keys)
    critic = ag.make_critic(ALGO_CFG, env, keys)
    loss = ag.make_loss(ALGO_CFG, actor, critic, env, keys)
    ag.make_target_updater(ALGO_CFG, loss)
    batch = _batch(env, keys)

    la, _ = loss.actor_loss(batch)
    la.backward()
    assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in actor.parameters())
    assert all(p.grad is None for p in critic.parameters())
    actor.zero_grad(set_to_none=True)

    lq, _ = loss.value_loss(batch)
    lq.backward()
    assert all(p.grad is None for p in actor.parameters())
    grads = [p.grad for p in critic.parameters()]
    assert all(g is not None for g in grads) and sum(float(g.abs().sum()) for g in grads) > 0
    # target networks never get gradients
    assert all(not t.requires_grad for t in loss.target_qvalue_network_params.values(True, True))


def test_ddpg_loss_equals_torchrl_ddpgloss():
    from torchrl.modules import Actor, ValueOperator
    from torchrl.objectives import DDPGLoss as TorchRLDDPGLoss

    torch.manual_seed(0)
    keys = ["rangefinder", "state"]
    env = make_toy_env()
    cfg = OmegaConf.merge(ALGO_CFG, {"encoder": {"augment_shift": 0}})
    ag = agents.get("ddpg")
    actor, critic = ag.make_actor(cfg, env, keys), ag.make_critic(cfg, env, keys)
    ours = ag.make_loss(cfg, actor, critic, env, keys)
    ag.make_target_updater(cfg, ours)

    class OneCritic(nn.Module):
        def forward(self, rf, st, a):
            return critic(rf, st, a)[0]

    ref = TorchRLDDPGLoss(Actor(actor, in_keys=keys, spec=env.action_spec), ValueOperator(OneCritic(), in_keys=[*keys, "action"]),
                          loss_function="l2", delay_actor=False, delay_value=False)
    ref.make_value_estimator(gamma=float(cfg.gamma))
    batch = _batch(env, keys)
    batch["next", "terminated"][:3] = True
    batch["next", "done"][:3] = True
    r = ref(batch.clone())
    la, _ = ours.actor_loss(batch.clone())
    lq, _ = ours.value_loss(batch.clone())
    torch.testing.assert_close(la, r["loss_actor"])
    torch.testing.assert_close(lq, r["loss_value"])


def test_td3_target_is_clipped_double_q_with_terminal_mask():
    torch.manual_seed(0)
    keys = ["rangefinder", "state"]
    env = make_toy_env()
    cfg = OmegaConf.merge(ALGO_CFG, {"policy_noise": 0.0, "encoder": {"augment_shift": 0}})
    ag = agents.get("td3")
    actor, critic = ag.make_actor(cfg, env, keys), ag.make_critic(cfg, env, keys)
    loss = ag.make_loss(cfg, actor, critic, env, keys)
    ag.make_target_updater(cfg, loss)
    batch = _batch(env, keys)
    batch["next", "terminated"][0] = True
    target, _ = loss.target(batch)
    nxt = [batch["next", k] for k in keys]
    q = critic(*nxt, actor(*nxt)).squeeze(-1)  # targets == online weights right after the updater's init
    want = batch["next", "reward"].squeeze(-1) + cfg.gamma * q.min(0).values
    want[0] = batch["next", "reward"][0, 0]
    torch.testing.assert_close(target, want)


def test_soft_update_moves_bound_target_networks():
    torch.manual_seed(0)
    keys = ["rangefinder", "state"]
    env = make_toy_env()
    ag = agents.get("td3")
    actor, critic = ag.make_actor(ALGO_CFG, env, keys), ag.make_critic(ALGO_CFG, env, keys)
    loss = ag.make_loss(ALGO_CFG, actor, critic, env, keys)
    upd = ag.make_target_updater(OmegaConf.merge(ALGO_CFG, {"tau": 0.5}), loss)
    x = [torch.rand(3, 19) * 50, torch.zeros(3, 6)]
    before = loss.target_actor(*x).clone()
    with torch.no_grad():
        for p in actor.parameters():
            p.add_(0.1)
    upd.step()
    after = loss.target_actor(*x)
    assert not torch.allclose(before, after)
    w_t = loss.target_actor.net[0].weight
    w = actor.net[0].weight
    torch.testing.assert_close(w_t, w - 0.05)


def test_c51_projection_hand_computed():
    support = torch.tensor([-2.0, -1.0, 0.0, 1.0, 2.0])
    p = torch.tensor([[0.1, 0.2, 0.4, 0.2, 0.1], [0.0, 0.0, 1.0, 0.0, 0.0], [0.5, 0.0, 0.0, 0.0, 0.5]])
    r = torch.tensor([0.5, 5.0, 0.0])
    g = torch.tensor([0.5, 0.9, 0.0])  # last row: terminal
    out = categorical_projection(p, r, g, support)
    # row 0: Tz = 0.5 + 0.5 z = [-0.5, 0, 0.5, 1, 1.5]
    #   -0.5 -> .5 on -1, .5 on 0 ; 0 -> 0 ; 0.5 -> .5 on 0, .5 on 1 ; 1 -> 1 ; 1.5 -> .5 on 1, .5 on 2
    want0 = torch.tensor([0.0, 0.05, 0.05 + 0.2 + 0.2, 0.2 + 0.2 + 0.05, 0.05])
    # row 1: Tz = 5 + 0.9 z clamps to 2 -> all mass on the top atom
    want1 = torch.tensor([0.0, 0.0, 0.0, 0.0, 1.0])
    # row 2: terminal, Tz = r = 0 for every atom -> all mass on 0
    want2 = torch.tensor([0.0, 0.0, 1.0, 0.0, 0.0])
    torch.testing.assert_close(out, torch.stack([want0, want1, want2]))
    torch.testing.assert_close(out.sum(-1), torch.ones(3))


def test_fused_soft_update_equals_torchrl_soft_update():
    from torchrl.objectives import SoftUpdate

    torch.manual_seed(0)
    keys = ["rangefinder", "state"]
    env = make_toy_env()
    ag = agents.get("td3")
    losses = []
    for _ in range(2):
        torch.manual_seed(0)
        actor, critic = ag.make_actor(ALGO_CFG, env, keys), ag.make_critic(ALGO_CFG, env, keys)
        losses.append(ag.make_loss(ALGO_CFG, actor, critic, env, keys))
    ours, ref = ag.make_target_updater(ALGO_CFG, losses[0]), SoftUpdate(losses[1], tau=float(ALGO_CFG.tau))
    for step in range(3):
        for loss in losses:
            with torch.no_grad():
                for p in loss.parameters():
                    p.add_(0.01 * (step + 1))
        ours.step()
        ref.step()
    for a, b in zip(losses[0].target_qvalue_network_params.values(True, True), losses[1].target_qvalue_network_params.values(True, True)):
        assert torch.equal(a, b)
    for a, b in zip(losses[0].target_actor_network_params.values(True, True), losses[1].target_actor_network_params.values(True, True)):
        assert torch.equal(a, b)


@pytest.mark.parametrize("algo", agents.OFF_POLICY)
def test_bfloat16_updates_are_mixed_precision_and_close_to_float32(algo):
    """algo.precision=bfloat16: matmuls in bf16, but weights, grads, optimiser state, Q and the losses stay float32,
    and one update moves the weights as the float32 update does (to bf16 accuracy)."""
    from torcsrl.agents._build import update

    keys = ["rangefinder", "state"]
    env = make_toy_env(sensors=keys)
    ag = agents.get(algo)
    runs = {}
    for prec in ("float32", "bfloat16"):
        torch.manual_seed(0)
        cfg = OmegaConf.merge(ALGO_CFG, {"actor_hidden": [64, 64], "critic_hidden": [64, 64], "precision": prec})
        actor, critic = ag.make_actor(cfg, env, keys), ag.make_critic(cfg, env, keys)
        loss = ag.make_loss(cfg, actor, critic, env, keys)
        optim, upd = ag.make_optimizers(cfg, loss), ag.make_target_updater(cfg, loss)
        torch.manual_seed(1)
        batch = _batch(env, keys, n=64)
        before = [p.detach().clone() for p in critic.parameters()]
        with torch.random.fork_rng():
            out = update(loss, optim, upd, batch, 0, policy_delay=1, grad_clip=None, precision=prec)
        assert all(p.dtype == torch.float32 for p in [*actor.parameters(), *critic.parameters()])
        assert all(s["exp_avg"].dtype == torch.float32 for o in optim.values() for s in o.state.values())
        assert out["loss/qvalue"].dtype == torch.float32 and torch.isfinite(out["loss/qvalue"])
        if algo != "d4pg":
            with torch.autocast("cpu", dtype=torch.bfloat16, enabled=prec == "bfloat16"), torch.no_grad():
                q = critic(*[batch[k] for k in keys], batch["action"])
            assert q.dtype == torch.float32  # the scalar Q head runs in float32 under autocast
        runs[prec] = (float(out["loss/qvalue"]), [p.detach() - b for p, b in zip(critic.parameters(), before)])
    (l32, d32), (l16, d16) = runs["float32"], runs["bfloat16"]
    assert l16 == pytest.approx(l32, rel=0.05)
    cos = torch.nn.functional.cosine_similarity(torch.cat([d.flatten() for d in d32]), torch.cat([d.flatten() for d in d16]), dim=0)
    assert cos > 0.9  # the same step direction (Adam's first step is sign-like: a different direction would show)


def test_unknown_precision_is_one_clear_line():
    from torcsrl.agents._build import precision_context

    with pytest.raises(ValueError, match="algo.precision='fp16' is not known; allowed: float32, bfloat16"):
        precision_context("fp16", "cpu")


def _sac(cfg_over=None):
    cfg = OmegaConf.merge(ALGO_CFG, {"encoder": {"augment_shift": 0}, **(cfg_over or {})})
    keys = ["rangefinder", "state"]
    env = make_toy_env()
    ag = agents.get("sac")
    actor, critic = ag.make_actor(cfg, env, keys), ag.make_critic(cfg, env, keys)
    loss = ag.make_loss(cfg, actor, critic, env, keys)
    ag.make_target_updater(cfg, loss)
    return env, keys, actor, critic, loss


def test_sac_target_is_soft_clipped_double_q_with_the_online_policy():
    torch.manual_seed(0)
    env, keys, actor, critic, loss = _sac({"alpha_init": 0.3})
    batch = _batch(env, keys)
    batch["next", "terminated"][0] = True
    torch.manual_seed(5)
    target, _ = loss.target(batch)
    nxt = [batch["next", k] for k in keys]
    torch.manual_seed(5)
    a, logp, _ = actor.sample(*nxt)  # the same draw
    with torch.no_grad():
        v = critic(*nxt, a).squeeze(-1).min(0).values - 0.3 * logp  # targets == online weights right after the updater's init
    want = batch["next", "reward"].squeeze(-1) + ALGO_CFG.gamma * v
    want[0] = batch["next", "reward"][0, 0]
    torch.testing.assert_close(target, want)
    assert not any(k.startswith("target_actor") for k in loss.state_dict())  # no target actor: the targets act with the online policy


def test_sac_temperature_moves_towards_the_target_entropy_and_only_it():
    torch.manual_seed(0)
    env, keys, actor, critic, loss = _sac()
    assert loss.target_entropy == -2.0  # "auto": minus the action size
    batch = _batch(env, keys)
    la, meta = loss.actor_loss(batch)
    for logp, sign in ((torch.full((8,), 5.0), -1), (torch.full((8,), -5.0), 1)):  # entropy too low: alpha grows; too high: shrinks
        loss.log_alpha.grad = None
        loss.alpha_loss(logp).backward()
        assert torch.sign(loss.log_alpha.grad) == sign
    assert all(p.grad is None for p in [*actor.parameters(), *critic.parameters()])
    g = loss.log_alpha.grad.clone()
    la.backward()  # the actor loss treats alpha as a constant
    assert torch.equal(loss.log_alpha.grad, g)
    assert set(meta) >= {"entropy", "alpha", "_action", "_q", "_log_prob"}


def test_ppo_gradients_reach_only_their_own_networks():
    torch.manual_seed(0)
    keys = ["rangefinder", "state", "pixels"]
    env = make_toy_env(sensors=keys, camera={"height": 16, "width": 16})
    cfg = OmegaConf.merge(ALGO_CFG, {"obs_norm": True, "entropy_coef": 0.01})
    ag = agents.get("ppo")
    actor, critic = ag.make_actor(cfg, env, keys), ag.make_critic(cfg, env, keys)
    loss = ag.make_loss(cfg, actor, critic, env, keys)
    assert ag.make_target_updater(cfg, loss) is None
    with torch.no_grad():
        data = env.rollout(16, ag.make_exploration(cfg, actor, env, keys), break_when_any_done=False)
        loss.value_estimator(data)
    assert {"advantage", "value_target"} <= set(data.keys())
    out = loss(data)
    (out["loss_objective"] + out["loss_entropy"]).backward(retain_graph=True)
    assert all(p.grad is None for p in critic.parameters())
    assert sum(float(p.grad.abs().sum()) for p in actor.parameters() if p.grad is not None) > 0
    actor.zero_grad(set_to_none=True)
    out["loss_critic"].backward()
    assert all(p.grad is None for p in actor.parameters())
    assert all(p.grad is not None for p in critic.net.parameters())
