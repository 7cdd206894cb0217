"""What the degradations do, checked against their models."""

from __future__ import annotations

import math

import pytest
import torch
from tensordict import TensorDict
from torchrl.envs import Compose

from _toy_sensor_env import ToySensorEnv
from _transform_helpers import deviation, make
from torcsrl.transforms import (
    BeamDropout,
    BeamFog,
    BeamNoise,
    BeamQuantize,
    DeadBeams,
    DegradedEnv,
    Fog,
    KeepClean,
    Latency,
    Mud,
    Occlusion,
    ScanDrop,
    StuckBeams,
    degradation_names,
)
from torcsrl.transforms.synthetic import road_frame


def _scans(values, n=4):
    return TensorDict({"rangefinder": torch.as_tensor(values, dtype=torch.float32).expand(n, -1).clone()}, [n])


# ------------------------------------------------------------------------ rangefinder
@pytest.mark.parametrize("severity,r_eff", [(1, 460.5), (2, 230.3), (3, 115.1), (4, 76.8), (5, 38.4)])
def test_fog_removes_beams_beyond_r_eff(severity, r_eff):
    r = torch.linspace(1.0, 199.0, 199)
    out = BeamFog(severity, p_spurious=0.0, seed=0)(_scans(r))["rangefinder"]
    beyond = r > r_eff
    assert (out[:, beyond] == 200.0).all()
    assert torch.equal(out[:, ~beyond], r[~beyond].expand(4, -1))
    assert math.isclose(math.log(100) / (2 * BeamFog.ladder["alpha"][severity - 1]), r_eff, rel_tol=1e-3)


def test_fog_spurious_returns_are_near():
    r = torch.full((19,), 100.0)
    out = BeamFog(5, alpha=1e-6, p_spurious=0.5, seed=0)(_scans(r, 256))["rangefinder"]
    hit = out < 100.0
    assert 0.4 < hit.float().mean() < 0.6
    assert out[hit].mean() < 10.0  # Exp(5 m)


def test_quantize_rounds_to_step():
    r = torch.rand(4, 19) * 150
    out = BeamQuantize(5, seed=0)(TensorDict({"rangefinder": r}, [4]))["rangefinder"]
    assert torch.allclose(out / 0.5, (out / 0.5).round(), atol=1e-4)
    assert (out - r).abs().max() <= 0.25 + 1e-4


def test_dropout_rate_matches_p():
    out = BeamDropout(5, seed=0)(_scans(torch.full((19,), 50.0), 2000))["rangefinder"]
    assert abs((out == 200.0).float().mean().item() - 0.35) < 0.02


def test_noise_sigma_grows_with_range():
    near = BeamNoise(5, seed=0)(_scans(torch.full((19,), 5.0), 2000))["rangefinder"]
    far = BeamNoise(5, seed=0)(_scans(torch.full((19,), 150.0), 2000))["rangefinder"]
    assert abs(near.std().item() - (0.5 + 0.05 * 5)) < 0.05
    assert abs(far.std().item() - (0.5 + 0.05 * 150)) < 0.4


def _rollout(transform, n=2, steps=12, keys=("rangefinder",)):
    env = DegradedEnv(ToySensorEnv([n], offtrack=False), Compose(KeepClean(list(keys)), transform))
    env.set_seed(0)
    return env, env.rollout(steps, break_when_any_done=False)


def _series(td, key):
    """[n, T+1, ...]: the reset reading followed by each step's."""
    return torch.cat([td[key][:, :1], td["next", key]], 1)


@pytest.mark.parametrize("k", [1, 3, 8])
@pytest.mark.parametrize("key", ["rangefinder", "pixels", "state"])
def test_latency_delays_by_exactly_k_steps(k, key):
    _, td = _rollout(Latency(steps=k, in_keys=[key]), keys=(key,))
    deg, clean = _series(td, key), _series(td, key + "_clean")
    T = deg.shape[1]
    for t in range(T):
        assert torch.equal(deg[:, t], clean[:, max(t - k, 0)]), (t, k)


def test_latency_jitter_stays_within_one_step():
    _, td = _rollout(Latency(4), n=4, steps=30)  # s4: 5 steps ± 1
    deg, clean = _series(td, "rangefinder"), _series(td, "rangefinder_clean")
    for t in range(8, deg.shape[1]):
        lags = [j for j in (4, 5, 6) if torch.equal(deg[0, t], clean[0, t - j])]
        assert lags, t


def test_latency_partial_reset_keeps_other_envs_history():
    t = Latency(steps=2, in_keys=["rangefinder"])
    env = DegradedEnv(ToySensorEnv([2], offtrack=False), Compose(KeepClean(["rangefinder"]), t))
    env.set_seed(0)
    td = env.reset()
    clean = [td["rangefinder_clean"]]
    for _ in range(4):
        td = env.step(env.rand_action(td))["next"]
        clean.append(td["rangefinder_clean"])
    reset = TensorDict({"_reset": torch.tensor([[True], [False]])}, [2])
    td = env.reset(td.update(reset))
    # env 0 restarted: no past; env 1 untouched by the reset
    assert torch.equal(td["rangefinder"][0], td["rangefinder_clean"][0])
    td = env.step(env.rand_action(td))["next"]
    clean.append(td["rangefinder_clean"])
    assert torch.equal(td["rangefinder"][1], clean[-3][1])


def test_dead_beams_persist_and_change_on_reset():
    t = DeadBeams(3, seed=0)
    env = DegradedEnv(ToySensorEnv([8], offtrack=False), Compose(KeepClean(["rangefinder"]), t))
    env.set_seed(0)
    td = env.rollout(10, break_when_any_done=False)
    dead = _series(td, "rangefinder") == 200.0
    assert (dead == dead[:, :1]).all(), "dead beams must persist through the episode"
    assert (dead[:, 0].sum(-1) == 3).all()
    first = t.dead_mask(19).clone()
    assert torch.equal(first, dead[:, 0])
    # a partial reset redraws only the envs being reset
    reset = torch.zeros(8, 1, dtype=torch.bool)
    reset[:4] = True
    td0 = env.reset(TensorDict({"_reset": reset}, [8]))
    after = t.dead_mask(19)
    assert torch.equal(after[4:], first[4:])
    assert not torch.equal(after[:4], first[:4])
    env.reset()
    assert not torch.equal(t.dead_mask(19), first)
    del td0


def test_stuck_beams_freeze():
    t = StuckBeams(5, onset_max=0, seed=0)  # s5: 4 beams stuck from the first reading
    _, td = _rollout(t, n=3, steps=10)
    deg, clean = _series(td, "rangefinder"), _series(td, "rangefinder_clean")
    frozen = (deg == deg[:, :1]).all(1)
    moving = ~(clean == clean[:, :1]).all(1)
    stuck = frozen & moving
    assert (stuck.sum(-1) == 4).all()
    assert torch.equal(deg[~stuck.unsqueeze(1).expand_as(deg)], clean[~stuck.unsqueeze(1).expand_as(clean)])


def test_scan_drop_holds_previous():
    _, td = _rollout(ScanDrop(5), n=4, steps=40)
    deg, clean = _series(td, "rangefinder"), _series(td, "rangefinder_clean")
    held = 0
    for t in range(1, deg.shape[1]):
        fresh = (deg[:, t] == clean[:, t]).all(-1)
        hold = (deg[:, t] == deg[:, t - 1]).all(-1)
        assert (fresh | hold).all()
        held += int((hold & ~fresh).sum())
    assert 10 < held < 60  # p = 0.2 of 160 steps


def test_offtrack_scans_pass_through_every_rangefinder_degradation():
    td = _scans(torch.full((19,), -1.0), 8)
    for name in degradation_names("rangefinder"):
        out = make(name, 5)(td.clone())
        assert (out["rangefinder"] == -1).all(), name


def test_severity_range_drawn_per_env_and_redrawn_only_on_reset():
    t = BeamNoise((1, 5), seed=0)
    env = DegradedEnv(ToySensorEnv([64]), t)
    env.reset()
    sev = t._state["severity"].clone()
    assert sev.unique().numel() == 5 and sev.min() >= 1 and sev.max() <= 5
    env.rollout(3, break_when_any_done=False, auto_reset=False, tensordict=env.reset())
    reset = torch.zeros(64, 1, dtype=torch.bool)
    reset[:32] = True
    sev = t._state["severity"].clone()
    env.reset(TensorDict({"_reset": reset}, [64]))
    new = t._state["severity"]
    assert torch.equal(new[32:], sev[32:]) and not torch.equal(new[:32], sev[:32])


# ------------------------------------------------------------------------ camera
def test_camera_fog_uses_depth():
    H = W = 32
    pix = torch.zeros(1, 3, H, W, dtype=torch.uint8)
    depth = torch.linspace(1.0, 200.0, W).view(1, 1, 1, W).expand(1, 1, H, W).clone()
    td = TensorDict({"pixels": pix, "depth": depth}, [1])
    out = Fog(4, seed=0)(td)["pixels"].float()
    row = out[0, 0, 0]
    assert (row[1:] >= row[:-1]).all() and row[-1] > row[0] + 50  # farther = foggier
    # I = A (1 - exp(-beta d)) for a black scene, d clipped at depth_scale
    expect = 0.8 * (1 - math.exp(-2.0 * 1.0)) * 255
    assert abs(row[-1].item() - expect) < 1.5


def test_camera_fog_row_proxy_without_depth():
    pix, _ = road_frame(48, 48)
    out = Fog(5, seed=0)(TensorDict({"pixels": pix.unsqueeze(0)}, [1]))["pixels"][0].float()
    gray = torch.full_like(out, 0.8 * 255)
    dev = (out - gray).abs().mean(dim=(0, 2))  # per row: distance from the airlight
    assert dev[:20].mean() < dev[-10:].mean()  # sky (far) is foggier than the near road


def test_fog_invalidates_far_depth():
    depth = torch.linspace(1.0, 300.0, 32).view(1, 1, 1, 32).expand(1, 1, 32, 32).clone()
    td = TensorDict({"pixels": torch.zeros(1, 3, 32, 32, dtype=torch.uint8), "depth": depth}, [1])
    out = Fog(4, in_keys=["pixels", "depth"], seed=0)(td)["depth"]
    # beta = 2, d/100 clipped to 1: t >= e^-2 > .05 everywhere; at beta 5, t < .05 beyond 60 m
    assert torch.equal(out, depth)
    out = Fog(5, beta=5.0, in_keys=["pixels", "depth"], seed=0)(td)["depth"]
    far = depth > 100 * math.log(20) / 5
    assert (out[far] == 0).all() and torch.equal(out[~far], depth[~far])


@pytest.mark.parametrize("cls,area", [(Mud, 0.18), (Occlusion, 0.18)])
def test_covered_area_matches_severity(cls, area):
    pix = torch.full((32, 3, 84, 84), 255, dtype=torch.uint8)
    out = cls(4, seed=0)(TensorDict({"pixels": pix}, [32]))["pixels"]
    covered = (out.float().mean(1) < 200).float().mean().item()
    lo = 0.5 * area if cls is Occlusion else 0.7 * area  # rectangles may overlap
    assert lo < covered < 1.3 * area


@pytest.mark.parametrize("name", degradation_names("camera"))
def test_same_look_at_64_and_84_px(name):
    """Lengths are fractions of the frame: the deviation from clean barely depends on size."""
    devs = []
    for size in (64, 84):
        pix, depth = road_frame(size, size)
        td = TensorDict({"pixels": pix.expand(16, -1, -1, -1).clone(), "depth": depth.expand(16, -1, -1, -1).clone()}, [16])
        clean = td.clone()
        out = make(name, 4, seed=5)(td)
        devs.append(deviation(out["pixels"], clean["pixels"]))
    if devs[0] == devs[1] == 0:  # temporal: identity on a snapshot
        return
    ratio = devs[1] / devs[0]
    assert 0.7 < ratio < 1.4, (name, devs)


def test_synthetic_depth_matches_the_ground_model():
    from torcsrl.transforms.camera import ground_distance

    H = 48
    pix, depth = road_frame(H, H, car=False)
    g = ground_distance(H, 8.0, 3.0, 60.0, z_depth=True).clamp(max=1000.0)
    assert torch.allclose(depth[0, :, 0], g, rtol=1e-4)
    r = ground_distance(H, 1.07, 8.0, 60.0)  # the hood camera: horizon 38 % down the frame
    assert torch.isinf(r[: int(0.37 * H)]).all() and torch.isfinite(r[int(0.39 * H) + 1 :]).all()
    bottom = math.atan((0.5 - 0.5 / H) * 2 * math.tan(math.radians(30))) + math.radians(8)
    assert r[-1].item() == pytest.approx(1.07 / math.sin(bottom), rel=1e-4)


def test_gallery_frame_sources(tmp_path):
    import cv2

    from torcsrl.transforms.gallery import _sequence, load_frame_source

    pix, _ = road_frame(40, 40)
    path = tmp_path / "frame.png"
    cv2.imwrite(str(path), pix.permute(1, 2, 0).numpy()[:, :, ::-1])
    fn = load_frame_source(str(path))
    pixs, depths = _sequence(fn, 32, 32, 3)
    assert pixs.shape == (3, 3, 32, 32) and pixs.dtype == torch.uint8 and depths is None
    pixs, depths = _sequence(load_frame_source("torcsrl.transforms.synthetic:road_frame"), 32, 32, 2)
    assert depths.shape == (2, 1, 32, 32)
    with pytest.raises(FileNotFoundError):
        load_frame_source("no_such_file.png")
