"""``device`` places the networks, the losses (targets included), the optimiser state and the sampled batches; the
envs, the collector, the replay buffer and the behaviour policy's input and output stay on the CPU.

Without a GPU here, placement is checked on ``device=cpu`` through the whole loop, and on torch's ``meta`` device (a
device other than the CPU that every machine has) for the builders — a network or a loss buffer left behind on the CPU
fails there. ``test_cuda_smoke`` runs the loop on a GPU where there is one."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir

from torcsrl import agents
from torcsrl.agents.exploration import DeviceActorModule
from torcsrl.pipeline import make_train_env
from torcsrl.training import train
from torcsrl.training.common import make_networks
from torcsrl.utils.checkpoint import load_checkpoint

CONF = str(Path(__file__).resolve().parents[1] / "conf")


@pytest.fixture(autouse=True)
def _one_thread():
    torch.set_num_threads(1)


def cfg_for(*overrides: str):
    with initialize_config_dir(config_dir=CONF, version_base="1.3"):
        return compose("train", overrides=["env=toy", "debug=smoke", *overrides])


def _tensors(loss) -> dict[str, torch.Tensor]:
    """Every tensor a loss computes with: its state (online and target parameters, buffers) and its bound target copies."""
    out = dict(loss.state_dict())
    for name in ("target_actor", "target_qvalue"):
        mod = loss.__dict__[name]
        out.update({f"{name}.{k}": t for k, t in [*mod.named_parameters(), *mod.named_buffers()]})
    return out


@pytest.mark.parametrize("algo", ["td3", "d4pg"])
@pytest.mark.parametrize("asym", [False, True])
def test_networks_and_loss_go_where_device_says(algo, asym):
    cfg = cfg_for(f"algo={algo}", "env.sensors=[pixels,state]", *(["critic_obs_keys=[rangefinder,state]"] if asym else []))
    env = make_train_env(cfg)
    try:
        for device in (torch.device("cpu"), torch.device("meta")):
            actor, critic, loss = make_networks(cfg, agents.get(algo), env, ["pixels", "state"], device)
            placed = {k: t.device.type for k, t in _tensors(loss).items()}
            assert len(placed) > 20 and set(placed.values()) == {device.type}, {k: v for k, v in placed.items() if v != device.type}
            assert {p.device.type for p in [*actor.parameters(), *critic.parameters()]} == {device.type}
            optim = agents.get(algo).make_optimizers(cfg.algo, loss)
            assert {p.device.type for o in optim.values() for g in o.param_groups for p in g["params"]} == {device.type}
    finally:
        env.close()


def test_behaviour_policy_reads_and_writes_cpu_tensors_for_an_actor_elsewhere():
    """The collector's side of device=cuda, checked with the module that does it (on the CPU, values must be equal)."""
    cfg = cfg_for("algo=td3", "env.sensors=[pixels,state]")
    env = make_train_env(cfg)
    try:
        actor, _, _ = make_networks(cfg, agents.get("td3"), env, ["pixels", "state"], torch.device("cpu"))
        td = env.reset()
        plain = actor(td["pixels"], td["state"])
        mod = DeviceActorModule(actor, ["pixels", "state"], ["action"], torch.device("cpu"))
        out = mod(td.clone())
        assert out["action"].device.type == "cpu" and torch.equal(out["action"], plain)
    finally:
        env.close()


def test_device_cpu_runs_the_loop_on_the_cpu(tmp_path):
    r = train(cfg_for("algo=td3", "device=cpu", f"run_dir={tmp_path}", "total_frames=200", "env.sensors=[pixels,state]",
                      "critic_obs_keys=[rangefinder,state]", "checkpoint.buffer=false"))
    assert r["updates"] > 0 and math.isfinite(r["loss/qvalue"])
    ck = load_checkpoint(r["checkpoint"])
    assert {t.device.type for t in ck["loss"].values()} == {"cpu"}
    assert {t.device.type for o in ck["optim"].values() for st in o["state"].values() for t in st.values() if torch.is_tensor(t)} == {"cpu"}


ALGOS = ["ddpg", "td3", "d4pg", "sac", "ppo"]
PPO_SMALL = ["algo.rollout_steps=50", "algo.epochs=2", "algo.batch_size=32"]


@pytest.mark.parametrize("algo", ["ddpg", "td3", "d4pg", "sac"])
def test_every_algorithm_places_its_networks_and_optimisers(algo):
    """The off-policy algorithms' builders on torch's ``meta`` device: nothing a loss computes with stays on the CPU.
    (PPO's loss cannot be built there: TorchRL's ``ClipPPOLoss`` reads a value at construction; the CUDA smoke covers it.)"""
    cfg = cfg_for(f"algo={algo}", "env.sensors=[pixels,state]")
    env = make_train_env(cfg)
    try:
        actor, critic, loss = make_networks(cfg, agents.get(algo), env, ["pixels", "state"], torch.device("meta"))
        placed = {k: t.device.type for k, t in loss.state_dict().items()}
        assert placed and set(placed.values()) == {"meta"}, {k: v for k, v in placed.items() if v != "meta"}
        assert {p.device.type for p in [*actor.parameters(), *critic.parameters()]} == {"meta"}
        optim = agents.get(algo).make_optimizers(cfg.algo, loss)
        assert {p.device.type for o in optim.values() for g in o.param_groups for p in g["params"]} == {"meta"}
    finally:
        env.close()


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA here")
@pytest.mark.parametrize("algo", ALGOS)
def test_cuda_smoke_every_algorithm(algo, tmp_path):
    """``device=cuda`` trains each algorithm on pixels + state (PPO: its own loop, GAE on the GPU) and checkpoints."""
    r = train(cfg_for(f"algo={algo}", "device=cuda", f"run_dir={tmp_path}", "total_frames=200", "env.sensors=[pixels,state]",
                      *(PPO_SMALL if algo == "ppo" else [])))
    assert r["updates"] > 0
    ck = load_checkpoint(r["checkpoint"])
    assert all(t.device.type == "cpu" for t in ck["loss"].values())


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA here")
def test_cuda_smoke(tmp_path):
    r = train(cfg_for("algo=td3", "device=cuda", f"run_dir={tmp_path}", "total_frames=200", "env.sensors=[pixels,state]",
                      "critic_obs_keys=[rangefinder,state]", "buffer.prioritized=true"))
    assert r["updates"] > 0 and math.isfinite(r["loss/qvalue"])
    ck = load_checkpoint(r["checkpoint"])  # loaded onto the CPU (map_location), written from the GPU
    assert all(t.device.type == "cpu" for t in ck["loss"].values())
