"""A check shared by the frame-stack and state-history tests: a checkpoint policy that keeps its own history, fed a
plain one-frame env, gives its actor exactly what the training env (with the stacking transform) gives it."""

from __future__ import annotations

import torch


def assert_policy_history_matches_training_env(pol, cfg, steps: int, action=lambda t: (0.0, 0.5)):
    """Drive the run's training env and a one-frame env of the same config (5-step episodes) side by side for
    ``steps`` steps with ``action(t)``; at every step the policy's own stack must equal the training env's. Returns
    the training env's last observation."""
    from torchrl.envs.utils import step_mdp

    from torcsrl.envs import make_env
    from torcsrl.pipeline import env_kwargs, make_train_env

    train_env = make_train_env(cfg)
    raw = make_env(**env_kwargs(cfg.env, seed=int(cfg.seed), device="cpu", max_steps=5))
    try:
        pol.check_env(raw)
        a, b = train_env.reset(), raw.reset()
        pol.reset()
        for t in range(steps):  # across the end of the raw env's 5-step episode: both reset
            with torch.no_grad():
                mine, want = pol._act(*(b.get(k) for k in pol.obs_keys)), pol.actor(*(a.get(k) for k in pol.obs_keys))
            torch.testing.assert_close(mine, want)
            act = torch.tensor(action(t), dtype=torch.float32)
            a, b = train_env.step(a.set("action", act)), raw.step(b.set("action", act))
            if bool(b["next", "done"]):
                a, b = train_env.reset(), raw.reset()
                pol.reset()
            else:
                a, b = step_mdp(a), step_mdp(b)
        return a
    finally:
        train_env.close()
        raw.close()
