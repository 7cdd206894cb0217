"""Where a student and its teacher part: drive a checkpoint on one track and surface while the teacher labels every
state the student reaches (the DAgger view), and print the per-step gap.

    python benchmarks/teacher_gap.py CKPT --track oval --surface asphalt [--teacher sensor_sight] [--steps 1500]
        [--frames out.png] [--driver student|teacher]

Prints how the episode ended, the mean |steer| and |pedal| gaps, the fraction of steps each brakes (pedal < 0),
and the last 40 steps (distance from start [m], speedX [km/h], trackPos, angle [rad], the student's and the
teacher's steer and pedal; for a student with a grip head, ``algo.grip_estimate``, its estimate of mu and the road's mu,
with the estimate's RMSE over the episode). ``--frames`` writes every 10th camera frame of the last 70 steps, labelled with the
speed and the teacher's pedal, to a PNG (camera students). This is how the sight-200 m teacher's camera student was
found never to brake on asphalt (torcsrl/assets/reference_camera.md).

``--driver teacher`` lets the teacher drive and scores the student on the teacher's own states (what behaviour cloning
fitted): it then prints the student's and the teacher's pedal around each braking onset of the teacher. A student
that brakes as hard as its teacher there but not on its own states suffers covariate shift (more DAgger); one that
brakes less there too cannot read the bend from the image.

``--opponents K`` races the student against K scripted experts at ``--pace`` (the race protocol of ``evaluate
mode=race``: a grid, its order drawn from ``--seed``) while a racer teacher (``--teacher racer_safe:1.5``, any
``racer*`` spec) labels every state with the opponents it sees. It prints the race position, contacts and overtakes,
and splits the gaps into the steps with a car within ``--near-m`` [m] (the nearest opponents sector) and the steps
clear of one: a student that follows its teacher alone but not in a fight (or the reverse) shows it here. The table
gains the nearest car's distance [m] (200: none in range). An ensemble file (``python -m torcsrl.policies ensemble``)
is scored as it drives: its members' actions combined by its reduce, the grip estimate their mean, and a side guard's
correction applied to the clean opponents and trackPos readings (``--side-guard`` files: the shipped racer).

    python benchmarks/teacher_gap.py RACER.pt --track esses --opponents 3 --teacher racer_safe:1.5 --steps 3000
"""

from __future__ import annotations

import argparse

import numpy as np
import torch


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("checkpoint")
    ap.add_argument("--track", default="oval")
    ap.add_argument("--surface", default="asphalt")
    ap.add_argument("--teacher", default="sensor_sight", help="a demos.teacher name (torcsrl.demos.TEACHERS)")
    ap.add_argument("--steps", type=int, default=1500)
    ap.add_argument("--seed", type=int, default=123)
    ap.add_argument("--frames", default=None, help="PNG of the last frames (camera students)")
    ap.add_argument("--driver", choices=("student", "teacher"), default="student", help="whose action is applied")
    ap.add_argument("--opponents", type=int, default=0, help="scripted expert opponents on the grid (0: alone)")
    ap.add_argument("--pace", type=float, default=0.85, help="the opponents' fraction of the expert's speed profile")
    ap.add_argument("--near-m", type=float, default=15.0, help="a step is 'near a car' when one is closer than this [m]")
    a = ap.parse_args(argv)
    if a.opponents < 0:
        ap.error(f"--opponents must be >= 0, got {a.opponents}")
    if not 0.0 < a.near_m <= 200.0:
        ap.error(f"--near-m must be in (0, 200] m (the opponents sensor's range), got {a.near_m}")
    torch.set_num_threads(1)
    from omegaconf import OmegaConf
    from torchrl.envs.utils import step_mdp

    from torcsrl.training.demos import make_demo_env, make_teacher
    from torcsrl.envs.traffic import TrafficError, TrafficSpec
    from torcsrl.evaluate.race import race_traffic
    from torcsrl.policies import CheckpointPolicy, EnsemblePolicy, EpisodeContext, PolicyError, SideGuard, load_policy

    try:
        pol = load_policy(a.checkpoint)
    except PolicyError as err:
        ap.error(str(err))
    guard = pol if isinstance(pol, SideGuard) else None  # a guarded file: the guard corrects what its students combine
    if guard is not None:
        pol = guard.inner
    members = list(pol.members) if isinstance(pol, EnsemblePolicy) else [pol]  # an ensemble file: its reduce combines
    if not all(isinstance(m, CheckpointPolicy) for m in members):
        ap.error(f"{a.checkpoint} is a built-in driver; teacher_gap scores a trained student (a checkpoint or policy file)")
    reduce = pol.reduce if isinstance(pol, EnsemblePolicy) else None
    cfg = OmegaConf.create(members[0].config_yaml)  # the members of an ensemble share the run's observation pipeline
    cfg.env.track, cfg.env.surface = a.track, a.surface
    if "procedural" in cfg.env:  # a student of a procedural pool (track=procedural) drove pool tracks 80 % of the time
        cfg.env.procedural = None
    if a.opponents:
        if "opponents" not in pol.obs_keys:
            ap.error(f"--opponents needs a student that reads the opponents sensor; {a.checkpoint} reads {list(pol.obs_keys)}")
        cfg.env.traffic = race_traffic(a.opponents, a.pace)
        try:  # the env's own checks (pace range, grid slots): one line
            TrafficSpec.from_config(cfg.env.traffic)
        except TrafficError as err:
            ap.error(str(err))
    if cfg.get("demos") is not None:  # the episode cap is --steps (the run's demos.episode_steps would cut a race short)
        cfg.demos.episode_steps = int(a.steps) + 1
    env = make_demo_env(cfg, a.seed)
    core = env.base_env.core
    traffic = core.traffic if a.opponents else None
    teacher = make_teacher(a.teacher)
    grip = all(getattr(m.actor, "grip_head", None) is not None for m in members)  # algo.grip_estimate: the actor's own estimate of mu
    td = env.reset()
    teacher.reset(EpisodeContext(track=core.car_tracks[0], seed=a.seed, dt=float(core.dt)))
    rows, frames, near, end = [], [], [], "step cap"
    try:
        for t in range(a.steps):
            teacher(td)
            label = td.get("action").clone()
            with torch.no_grad():  # the demo env already applies the run's observation pipeline (scaling included):
                obs = [td.get(k) for k in pol.obs_keys]
                acts = torch.stack([m.actor(*obs).reshape(label.shape) for m in members])  # the actors, not pol(td)
                act = acts[0] if reduce is None else EnsemblePolicy.combine(acts, reduce)
                if guard is not None:  # it reads metres and trackPos: the env's readings before the run's pipeline
                    opp_m, st_raw = (td.get(f"{k}_clean").reshape(1, -1).float() for k in ("opponents", "state"))
                    act = guard.correct(act.reshape(1, -1), opp_m, st_raw[:, guard.tp_slot]).reshape(label.shape)
                mu_hat = (sum(float(m.actor.grip(m.actor.encoder(*obs))) for m in members) / len(members)) if grip else float("nan")
            td.set("action", act if a.driver == "student" else label)
            st = td.get("state_clean")
            rows.append((float(td.get(("info", "distFromStart"))), float(st[2]), float(st[1]), float(st[0]), *act.tolist(), *label.tolist(),
                         mu_hat, float(td.get(("info", "surfaceMu")).reshape(-1)[0])))
            if traffic is not None:  # the nearest car over the 36 sectors of the clean opponents reading [m]
                near.append(float(td.get("opponents_clean").reshape(-1).min()))
            if "pixels" in td.keys():
                frames.append(td.get("pixels")[-3:].clone())  # the newest frame (of a frame_stack student's stack)
            td = env.step(td)
            nxt = td.get("next")
            if bool(nxt.get("done").reshape(-1)[0]):
                end = f"{'terminated' if bool(nxt.get('terminated').reshape(-1)[0]) else 'truncated'} at step {t}, " \
                      f"{int(nxt.get(('info', 'lap')).reshape(-1)[0])} lap(s)"
                break
            td = step_mdp(td)
        race = None if traffic is None else (int(traffic.race_pos[0]), int(traffic.collisions[0]), int(traffic.overtakes[0]))
    finally:
        env.close()
    r = np.asarray(rows)
    gap = np.abs(r[:, 4:6] - r[:, 6:8])
    print(f"{a.checkpoint} on {a.track}/{a.surface}, teacher {a.teacher}, {a.driver} driving: {end}")
    print(f"mean |steer gap| {gap[:, 0].mean():.3f}, mean |pedal gap| {gap[:, 1].mean():.3f}; "
          f"brakes on {100 * (r[:, 5] < 0).mean():.0f} % of steps (teacher: {100 * (r[:, 7] < 0).mean():.0f} %)")
    if race is not None:
        d = np.asarray(near)
        print(f"race against {a.opponents} experts at pace {a.pace:g}: position {race[0]} of {a.opponents + 1} at the end, "
              f"{race[1]} contact(s), {race[2]} overtake(s)")
        for name, m in ((f"near a car (< {a.near_m:g} m)", d < a.near_m), ("clear of cars", d >= a.near_m)):
            if m.any():
                print(f"{name}: {int(m.sum())} steps, mean |steer gap| {gap[m, 0].mean():.3f}, mean |pedal gap| {gap[m, 1].mean():.3f}, "
                      f"mean pedal student {r[m, 5].mean():+.3f}, teacher {r[m, 7].mean():+.3f}")
            else:
                print(f"{name}: 0 steps")
    if grip:
        err = r[:, 8] - r[:, 9]
        print(f"grip estimate: mean {r[:, 8].mean():.3f} for the road's mu {r[:, 9].mean():.3f} (RMSE {np.sqrt((err ** 2).mean()):.3f}; "
              f"last 100 steps: mean {r[-100:, 8].mean():.3f})")
    else:
        r = r[:, :8]
    if race is not None:
        r = np.concatenate([r, np.asarray(near)[:, None]], axis=1)
    head = ("| dist m | speedX km/h | trackPos | angle rad | steer | pedal | teacher steer | teacher pedal |" + (" mu_hat | mu |" if grip else "")
            + (" nearest car m |" if race is not None else "") + "\n|" + "---|" * r.shape[1])
    if a.driver == "student":
        print(head)
        for row in r[-40::4]:
            print("| " + " | ".join(f"{v:.2f}" for v in row) + " |")
    else:
        hard = r[:, 7] < -0.3
        onsets = [i for i in range(1, len(r)) if r[i, 7] < -0.1 <= r[i - 1, 7]]
        print(f"where the teacher brakes harder than -0.3 ({int(hard.sum())} steps): mean pedal student "
              f"{r[hard, 5].mean() if hard.any() else float('nan'):+.3f}, teacher {r[hard, 7].mean() if hard.any() else float('nan'):+.3f}; "
              f"{len(onsets)} braking onsets")
        for i in onsets[:4]:
            print(head)
            for row in r[max(0, i - 2):i + 8]:
                print("| " + " | ".join(f"{v:.2f}" for v in row) + " |")
    if a.frames and frames:
        import cv2

        tiles = []
        for i in range(max(0, len(frames) - 70), len(frames), 10):
            im = np.ascontiguousarray(frames[i].numpy().transpose(1, 2, 0)[:, :, ::-1])
            im = cv2.resize(im, None, fx=4, fy=4, interpolation=cv2.INTER_NEAREST)
            cv2.putText(im, f"t{i} {r[i, 1]:.0f} km/h teacher pedal {r[i, 7]:+.2f}", (3, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (255, 255, 255), 1)
            tiles.append(im)
        while len(tiles) % 4:
            tiles.append(np.zeros_like(tiles[0]))
        cv2.imwrite(a.frames, np.concatenate([np.concatenate(tiles[i:i + 4], 1) for i in range(0, len(tiles), 4)], 0))
        print(f"wrote {a.frames}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
