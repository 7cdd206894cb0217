"""Cars that share a track: opponents, the start grid, contacts, race books and the ``opponents`` sensor.

A race env (``RaceCore(traffic={...})``) holds N *learners* (the cars the agent drives: the env's batch) and K
*opponents* per learner. Learner ``g`` and its K opponents form *race group* g: one copy of the track at its own
world origin (group g lies ``g x 10 km`` north of group 0, as the batched env already places tracks apart), so the
groups never meet while the cars of a group collide with each other (chassis boxes; pybullet contacts). Car order
in the core: learners first (``0 .. N-1``), then group 0's opponents, group 1's, ... (car ``N + g K + j``).

Opponents (``traffic.driver`` for all of them, ``traffic.drivers`` per car):

========  ==========================================================================================
kind      what drives it
========  ==========================================================================================
expert    the scripted expert (:class:`torcsrl.envs.expert.ExpertDriver`) on its ``line`` (racing |
          centre) at ``pace`` x its speed profile (a number, or ``[lo, hi]``: drawn per episode)
policy    a frozen checkpoint (``policy: <path>``): its deterministic actor on its own clean
          rangefinder / state / telemetry / opponents readings (never a camera)
slow      the expert on its line, capped at ``speed_kmh``
parked    stands still (brakes on) at a seeded spot of the lap, ``lateral`` of the half-width off the centre
========  ==========================================================================================

Scripted opponents (expert, slow) avoid the cars around them as TORCS's robots do, in the simplest form: they lift
and brake for a car close ahead on their line (:meth:`Traffic._follow_limit`), and with a car alongside they keep
``side_gap_m`` (3.2 m between centres) from it on their own side instead of turning in across it
(:meth:`Traffic._side_room`, after ``bt``'s ``filterSColl``; ``side_gap_m: 0`` gives the opponents of before
2026-11-27, blind to a car beside them).

Starts (``traffic.start``): ``grid`` — TORCS's staggered two-wide grid behind the line (slot k: row k // 2, left
column for even k), at rest; ``rolling`` — single file at ``rolling.speed_kmh``, ``rolling.gap_m`` apart. The order
of the cars on the grid is drawn per episode from the env's seed (``order: random``), or the learner takes
``learner_slot`` (``order: fixed``). With the env's ``start: random`` the grid is laid at a random point of the lap
(training meets every bend with traffic); with ``start: grid`` its front is the start/finish line.

The ``opponents`` observation (TORCS SCR's opponent sensor): 36 distances [m], one per 10-degree sector around the
car, each the centre-to-centre distance to the nearest other car of its group in that sector, capped at 200 m; a
free sector reads 200 (the SCR value). Sector k covers the directions whose angle *clockwise* from the car's heading
lies in ``[-180 + 10 k, -170 + 10 k)`` degrees — SCR's order: sector 0 looks straight back (from the left side),
8 and 9 to the left, 17 ahead-left, 18 ahead-right, 26 and 27 to the right, 35 back (right side). See
:func:`opponent_sectors`. The rangefinder never sees cars (its rays are cast against the track edges in a client
of their own).

Race books (per car, reported in ``info``): ``racePos`` (1 = leading its group), ``overtakes`` (other cars passed,
net of being re-passed by the same car), ``collisions`` (contacts begun with another car), ``damage`` (summed
contact impulse [kN s]), ``impulse`` (this step's contact impulse [kN s]) and ``gapAhead`` [m] (along-track distance
to the nearest car ahead in the race, 200 when none is within 200 m). Not in ``info``: ``contact_sides [n, 3]``, each
car's contacts by where the other car was when it began — ahead, alongside or behind (:attr:`Traffic.CONTACT_SIDES`);
the race evaluation reports them.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, fields, replace
from typing import Any

import numpy as np
from torcsrl.utils.bullet import pybullet as p

__all__ = ["OPPONENT_KINDS", "TrafficSpec", "DriverSpec", "TrafficError", "Traffic", "opponent_sectors", "sector_directions",
           "load_opponent_policy", "OPPONENT_SECTORS", "OPPONENT_RANGE_M", "RACE_INFO_KEYS", "OPPONENT_OBS_KEYS"]

OPPONENT_KINDS = ("expert", "policy", "slow", "parked")
START_KINDS = ("grid", "rolling")
ORDER_KINDS = ("random", "fixed")
#: Number of opponent sectors and their range [m] (TORCS SCR).
OPPONENT_SECTORS = 36
OPPONENT_RANGE_M = 200.0
#: Observation keys a frozen-policy opponent may read (the camera is never rendered for opponents).
OPPONENT_OBS_KEYS = ("rangefinder", "state", "telemetry", "opponents")
#: Race keys every car reports in ``info`` (see the module docstring).
RACE_INFO_KEYS = ("racePos", "overtakes", "collisions", "damage", "impulse", "gapAhead")
#: Opponents' chassis colour (the learner's is the fleet's red): blue.
OPPONENT_RGBA = (0.15, 0.3, 0.85, 1.0)


class TrafficError(ValueError):
    """A traffic setting the env cannot use (one line naming what is allowed)."""


def _num(v: Any, what: str, lo: float = 0.0, hi: float = math.inf) -> float:
    try:
        x = float(v)
    except (TypeError, ValueError):
        x = math.nan
    if not (math.isfinite(x) and lo <= x <= hi):
        raise TrafficError(f"traffic {what} must be a number in [{lo:g}, {hi:g}], got {v!r}")
    return x


@dataclass(frozen=True)
class DriverSpec:
    """One opponent's driver (see the module docstring)."""

    kind: str = "expert"
    pace: float | tuple[float, float] = 0.85
    line: str = "racing"
    policy: str | None = None
    speed_kmh: float = 60.0
    lateral: float = 0.5

    @classmethod
    def parse(cls, d: Any, where: str, base: DriverSpec | None = None) -> DriverSpec:
        if isinstance(d, DriverSpec):
            return d
        if d is None:
            return base or cls()
        if not isinstance(d, Mapping):
            raise TrafficError(f"traffic {where} must be a mapping {{kind, pace, line, policy, speed_kmh, lateral}}, got {d!r}")
        names = {f.name for f in fields(cls)}
        unknown = sorted(set(d) - names)
        if unknown:
            raise TrafficError(f"traffic {where}: unknown keys {unknown}; allowed: {', '.join(sorted(names))}")
        kw = {f.name: getattr(base or cls(), f.name) for f in fields(cls)}
        kw.update(dict(d))
        if kw["kind"] not in OPPONENT_KINDS:
            raise TrafficError(f"traffic {where}.kind {kw['kind']!r} is unknown; allowed: {', '.join(OPPONENT_KINDS)}")
        pace = kw["pace"]
        if isinstance(pace, (list, tuple)) or (hasattr(pace, "__iter__") and not isinstance(pace, str)):
            pace = tuple(pace)
            if len(pace) != 2:
                raise TrafficError(f"traffic {where}.pace must be a number or [lo, hi], got {list(pace)!r}")
            lo, hi = (_num(x, f"{where}.pace", 0.05, 1.5) for x in pace)
            if lo > hi:
                raise TrafficError(f"traffic {where}.pace [lo, hi] needs lo <= hi, got {list(pace)!r}")
            kw["pace"] = (lo, hi)
        else:
            kw["pace"] = _num(pace, f"{where}.pace", 0.05, 1.5)
        if kw["line"] not in ("racing", "centre"):
            raise TrafficError(f"traffic {where}.line {kw['line']!r} is unknown; allowed: racing, centre")
        kw["speed_kmh"] = _num(kw["speed_kmh"], f"{where}.speed_kmh", 1.0, 400.0)
        kw["lateral"] = _num(kw["lateral"], f"{where}.lateral", -1.0, 1.0)
        if kw["kind"] == "policy" and not kw["policy"]:
            raise TrafficError(f"traffic {where}: kind policy needs policy: <checkpoint path or reference name>")
        return cls(**kw)


@dataclass(frozen=True)
class TrafficSpec:
    """What :class:`Traffic` builds, from the ``traffic`` mapping of the env (conf/traffic/*.yaml)."""

    opponents: int = 3
    driver: DriverSpec = field(default_factory=DriverSpec)
    drivers: tuple[DriverSpec, ...] = ()
    start: str = "grid"
    order: str = "random"
    learner_slot: int | str = "last"
    collide: bool = True
    grid: Mapping[str, float] = field(default_factory=lambda: dict(GRID_DEFAULTS))
    rolling: Mapping[str, float] = field(default_factory=lambda: dict(ROLLING_DEFAULTS))
    safe_headway_s: float = 1.0
    safe_gap_min_m: float = 10.0
    block_range_m: float = 20.0
    side_gap_m: float = 3.2
    #: What turns an opponent's ``policy`` spec into a policy (``torcsrl.policies.load_policy``): handed in by whoever
    #: builds the env (``make_env(policy_loader=...)``, :meth:`with_policy_loader`), as the env layer loads no
    #: policies itself; not a config key.
    policy_loader: Callable[[str], Any] | None = field(default=None, compare=False, repr=False)

    @classmethod
    def from_config(cls, cfg: Any) -> TrafficSpec | None:
        """``None`` (or ``{opponents: 0}`` with nothing else) means no traffic."""
        if cfg is None or isinstance(cfg, TrafficSpec):
            return cfg
        if not isinstance(cfg, Mapping):
            raise TrafficError(f"traffic must be a mapping (conf/traffic/*.yaml) or null, got {cfg!r}")
        d = dict(cfg)
        names = {f.name for f in fields(cls)} - {"policy_loader"}
        unknown = sorted(set(d) - names)
        if unknown:
            raise TrafficError(f"traffic: unknown keys {unknown}; allowed: {', '.join(sorted(names))}")
        kw: dict[str, Any] = {}
        k = d.get("opponents", 3)
        if isinstance(k, bool) or not isinstance(k, (int, np.integer)) or k < 0:
            raise TrafficError(f"traffic opponents must be an integer >= 0, got {k!r}")
        kw["opponents"] = int(k)
        base = DriverSpec.parse(d.get("driver"), "driver")
        kw["driver"] = base
        per = d.get("drivers") or ()
        if not isinstance(per, (list, tuple)) and not hasattr(per, "__iter__"):
            raise TrafficError(f"traffic drivers must be a list (one mapping per opponent), got {per!r}")
        per = list(per)
        if len(per) > kw["opponents"]:
            raise TrafficError(f"traffic drivers lists {len(per)} opponents, but opponents = {kw['opponents']}; allowed: at most opponents entries")
        kw["drivers"] = tuple(DriverSpec.parse(x, f"drivers[{i}]", base) for i, x in enumerate(per))
        for key, allowed in (("start", START_KINDS), ("order", ORDER_KINDS)):
            v = d.get(key, getattr(cls, key))
            if v not in allowed:
                raise TrafficError(f"traffic {key} {v!r} is unknown; allowed: {', '.join(allowed)}")
            kw[key] = v
        ls = d.get("learner_slot", "last")
        if not (ls in ("first", "last") or (isinstance(ls, (int, np.integer)) and not isinstance(ls, bool) and ls >= 0)):
            raise TrafficError(f"traffic learner_slot must be first, last or a slot index >= 0, got {ls!r}")
        kw["learner_slot"] = ls
        kw["collide"] = bool(d.get("collide", True))
        for key, defaults in (("grid", GRID_DEFAULTS), ("rolling", ROLLING_DEFAULTS)):
            sub = dict(d.get(key) or {})
            bad = sorted(set(sub) - set(defaults))
            if bad:
                raise TrafficError(f"traffic {key}: unknown keys {bad}; allowed: {', '.join(defaults)}")
            merged = dict(defaults)
            for kk, vv in sub.items():
                merged[kk] = _num(vv, f"{key}.{kk}", 0.0, 1e4)
            kw[key] = merged
        if int(kw["grid"]["slots"]) != kw["grid"]["slots"] or kw["grid"]["slots"] < 1:
            raise TrafficError(f"traffic grid.slots must be a positive integer, got {kw['grid']['slots']!r}")
        for key in ("safe_headway_s", "safe_gap_min_m", "block_range_m", "side_gap_m"):
            if key in d:
                kw[key] = _num(d[key], key, 0.0, 1e4)
        spec = cls(**kw)
        cars = spec.opponents + 1
        if spec.start == "grid" and cars > int(spec.grid["slots"]):
            raise TrafficError(f"traffic: {cars} cars (1 learner + {spec.opponents} opponents) do not fit the grid of "
                               f"{int(spec.grid['slots'])} slots; allowed: opponents <= {int(spec.grid['slots']) - 1} "
                               "(or raise traffic.grid.slots)")
        if isinstance(ls, int) and ls >= cars:
            raise TrafficError(f"traffic learner_slot {ls} is beyond the {cars} cars of a group; allowed: 0..{cars - 1}, first, last")
        return spec

    def driver_of(self, j: int) -> DriverSpec:
        return self.drivers[j] if j < len(self.drivers) else self.driver

    def policy_specs(self) -> list[str]:
        return sorted({self.driver_of(j).policy for j in range(self.opponents) if self.driver_of(j).kind == "policy"})

    def with_policy_loader(self, loader: Callable[[str], Any] | None) -> TrafficSpec:
        """This traffic, its opponents' policies loaded by ``loader`` (a spec -> a policy; see :attr:`policy_loader`)."""
        if loader is not None and not callable(loader):
            raise TrafficError(f"traffic policy_loader must be a callable (a policy spec -> a policy), got {loader!r}")
        return replace(self, policy_loader=loader)


#: Grid geometry [m]: front of the grid behind the line (``front_m``), row spacing, the right column's stagger,
#: lateral offset as a fraction of the half-width, and how many cars it holds.
GRID_DEFAULTS = {"slots": 12, "front_m": 6.0, "row_m": 12.0, "stagger_m": 6.0, "lateral": 0.45}
#: Rolling start: speed [km/h] and the gap between consecutive cars [m].
ROLLING_DEFAULTS = {"speed_kmh": 80.0, "gap_m": 25.0}


def sector_directions(sectors: int = OPPONENT_SECTORS) -> tuple[np.ndarray, np.ndarray]:
    """``(cos, sin)`` ``[36]`` of the SCR opponents sectors' centres, ``175 - 10 k`` degrees counter-clockwise from the
    heading (sector 0 straight back from the left, 9 left, 17/18 ahead, 27 right): a car a sector shows at ``r`` m sits
    ``r cos`` ahead and ``r sin`` to the left. How the racing teacher and the side guard read the sensor."""
    phi = np.radians(175.0 - 10.0 * np.arange(sectors))
    return np.cos(phi), np.sin(phi)


def opponent_sectors(xy: np.ndarray, yaw: np.ndarray, groups: np.ndarray, active: np.ndarray | None = None,
                     sectors: int = OPPONENT_SECTORS, range_m: float = OPPONENT_RANGE_M) -> np.ndarray:
    """TORCS SCR's opponent sensor for every car: ``[n, sectors]`` float32 [m].

    Args:
        xy: car centres ``[n, 2]`` (world frame; cars of one group share a frame).
        yaw: headings ``[n]`` [rad].
        groups: race group of each car ``[n]``; a car sees only the cars of its group.
        active: cars that can be seen (None: all).

    Sector k of car i holds the smallest centre distance (< ``range_m``) of the other cars whose direction, measured
    clockwise from car i's heading (SCR: ``car_angle = yaw - bearing``) and wrapped into [-180, 180), lies in
    ``[-180 + k w, -180 + (k + 1) w)`` degrees (``w = 360 / sectors``); a free sector reads ``range_m``.
    """
    xy = np.asarray(xy, dtype=np.float64)
    n = len(xy)
    out = np.full((n, sectors), range_m, dtype=np.float32)
    if n < 2:
        return out
    d = xy[None, :, :] - xy[:, None, :]  # [i, j]: from car i to car j
    dist = np.hypot(d[..., 0], d[..., 1])
    ok = (groups[:, None] == groups[None, :]) & (dist < range_m)
    np.fill_diagonal(ok, False)
    if active is not None:
        ok &= np.asarray(active, dtype=bool)[None, :]
    i, j = np.nonzero(ok)
    if len(i) == 0:
        return out
    bearing = np.arctan2(d[i, j, 1], d[i, j, 0])
    car_angle = (np.degrees(np.asarray(yaw)[i] - bearing) + 180.0) % 360.0 - 180.0  # clockwise, [-180, 180)
    k = np.minimum(((car_angle + 180.0) * (sectors / 360.0)).astype(np.int64), sectors - 1)
    np.minimum.at(out, (i, k), dist[i, j].astype(np.float32))
    return out


class _TrackFrameFleet:
    """What :meth:`ExpertDriver.act` reads, for cars driving at an offset world origin."""

    def __init__(self, fleet, origins: np.ndarray) -> None:
        pos = fleet.pos.copy()
        pos[:, :2] -= origins
        self.pos = pos
        self.yaw, self.vel_body, self.yaw_rate = fleet.yaw, fleet.vel_body, fleet.yaw_rate
        self.speed, self.wheel_omega, self.dt_control = fleet.speed, fleet.wheel_omega, fleet.dt_control


class Traffic:
    """The opponents of a :class:`~torcsrl.envs.race.RaceCore` (built by the core; see the module docstring).

    Args:
        spec: the parsed settings.
        n_learners: N (race groups).
        params: the vehicle parameters (every car is the same car).
    """

    def __init__(self, spec: TrafficSpec, n_learners: int, params) -> None:
        self.spec = spec
        self.N = int(n_learners)
        self.K = int(spec.opponents)
        self.M = self.K + 1  # cars per group
        self.n = self.N * self.M
        self.params = params
        N, K = self.N, self.K
        #: race group of each car, and each group's cars (learner first)
        self.group = np.concatenate([np.arange(N), np.repeat(np.arange(N), K)]).astype(np.int64)
        self.members = np.array([[g] + [N + g * K + j for j in range(K)] for g in range(N)], dtype=np.int64)  # [N, M]
        self._members_of = [self.members[g].tolist() for g in self.group.tolist()]  # per car: its group's cars
        self.kinds = [spec.driver_of(j) for j in range(K)]  # per opponent slot j (same in every group)
        self._policies: dict[str, Any] = {}
        self._restarted: set[int] = set()  # policy-driven opponent cars whose episode restarted since their last step
        for path in spec.policy_specs():
            self._policies[path] = load_opponent_policy(path, spec.policy_loader)
        self._base_drivers: dict[tuple, Any] = {}
        self.drivers: list[Any] = [None] * (N * K)  # per opponent car (index car - N)
        self.pace = np.ones(N * K)
        # race books (per car, [n])
        n = self.n
        self.start_back = np.zeros(n)  # how far behind the race's start point the car started [m]
        self.race_pos = np.ones(n, dtype=np.int64)
        self.start_pos = np.ones(n, dtype=np.int64)
        self.overtakes = np.zeros(n, dtype=np.int64)
        self.collisions = np.zeros(n, dtype=np.int64)
        self.contact_sides = np.zeros((n, 3), dtype=np.int64)  # contacts begun with the other car ahead / alongside / behind
        self.damage = np.zeros(n)
        self.impulse = np.zeros(n)
        self.gap_ahead = np.full(n, OPPONENT_RANGE_M)
        self.ahead = np.zeros((N, self.M, self.M), dtype=bool)  # ahead[g, a, b]: car a ahead of car b
        self.touching = np.zeros((n, n), dtype=bool)
        self.terms = np.zeros((4, n))  # collision, positions, gap, blocking

    # ------------------------------------------------------------------ policies
    @property
    def obs_keys(self) -> tuple[str, ...]:
        """Observation keys the frozen-policy opponents read."""
        keys: list[str] = []
        for pol in self._policies.values():
            keys += [k for k in pol.obs_keys if k not in keys]
        return tuple(keys)

    # ------------------------------------------------------------------ episodes
    def _driver(self, track, j: int, pace: float):
        # deferred: the expert's racing line, only for scripted expert opponents
        from torcsrl.envs.expert import ExpertDriver

        ds = self.kinds[j]
        key = (id(track), ds.line)
        base = self._base_drivers.get(key)
        if base is None:
            base = self._base_drivers[key] = (ExpertDriver(track, self.params, line=ds.line), track)
        drv = copy.copy(base[0])
        v = np.asarray(base[0].v_ref, dtype=np.float64) * pace
        if ds.kind == "slow":
            v = np.minimum(np.asarray(base[0].v_ref), ds.speed_kmh / 3.6)
        if ds.kind == "slow" or pace != 1.0:
            ds_ = np.maximum(drv.line.ds, 1e-6)
            drv._v = v.tolist()
            drv._a = ((np.roll(v, -1) ** 2 - v ** 2) / (2.0 * ds_)).tolist()
        return drv

    def layout(self, g: int, track, rng: np.random.Generator, anchor: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Start poses of group ``g``'s cars (learner first): arc length ``s``, lateral ``d`` [m], speed [m/s],
        and how far behind ``anchor`` each starts [m]; draws the grid order and the paces from ``rng``."""
        spec, M, K = self.spec, self.M, self.K
        if spec.order == "random":
            order = rng.permutation(M)  # order[c]: grid slot of car c (c = 0: learner)
        else:
            ls = spec.learner_slot
            slot = 0 if ls == "first" else M - 1 if ls == "last" else int(ls)
            rest = [k for k in range(M) if k != slot]
            order = np.array([slot] + rest)
        paces = []
        for j, ds in enumerate(self.kinds):
            pace = rng.uniform(*ds.pace) if isinstance(ds.pace, tuple) else float(ds.pace)
            paces.append(pace)
        L = float(track.length)
        back = np.zeros(M)
        dd = np.zeros(M)
        speed = np.zeros(M)
        if spec.start == "grid":
            gr = spec.grid
            for c in range(M):
                k = int(order[c])
                back[c] = gr["front_m"] + (k // 2) * gr["row_m"] + (k % 2) * gr["stagger_m"]
            if back.max() > 0.5 * L:
                raise TrafficError(f"traffic: the grid of {M} cars reaches {back.max():.0f} m behind the line on "
                                   f"{track.name!r} ({L:.0f} m); allowed: a grid shorter than half the lap (fewer cars or a "
                                   "shorter grid.row_m)")
            for c in range(M):
                k = int(order[c])
                s = (anchor - back[c]) % L
                wl, wr = track.width(s)
                dd[c] = gr["lateral"] * (float(wl) if k % 2 == 0 else -float(wr))
        else:
            ro = spec.rolling
            back = (np.asarray(order, dtype=np.float64) + 1.0) * ro["gap_m"]
            if back.max() > 0.5 * L:
                raise TrafficError(f"traffic: the rolling start of {M} cars spans {back.max():.0f} m on {track.name!r} "
                                   f"({L:.0f} m); allowed: less than half the lap (fewer cars or a smaller rolling.gap_m)")
            speed[:] = ro["speed_kmh"] / 3.6
        s_start = (anchor - back) % L
        for j, ds in enumerate(self.kinds):  # parked cars stand somewhere down the road instead
            c = j + 1
            if ds.kind == "parked":
                s_p = (anchor + rng.uniform(0.15, 0.85) * L) % L
                wl, wr = track.width(s_p)
                s_start[c] = s_p
                dd[c] = ds.lateral * (float(wl) if ds.lateral >= 0 else float(wr))
                speed[c] = 0.0
                back[c] = -float((s_p - anchor) % L)
        # a car never starts faster than its own driver would drive there (rolling starts)
        for j in range(K):
            car = g * K + j
            ds = self.kinds[j]
            self.pace[car] = paces[j]
            if ds.kind in ("expert", "slow"):
                drv = self._driver(track, j, paces[j])
                drv.reset(float(s_start[j + 1]))
                self.drivers[car] = drv
                if speed[j + 1] > 0:
                    speed[j + 1] = min(speed[j + 1], float(np.interp(s_start[j + 1], drv.line.track_s, drv._v)))
            else:
                self.drivers[car] = None
                if ds.kind == "policy":  # a policy that keeps readings forgets this car's at its next step
                    self._restarted.add(self.N + car)
        for key in ("race_pos", "start_pos"):
            getattr(self, key)[self.members[g]] = 1 + np.argsort(np.argsort(back, kind="stable"), kind="stable")
        return s_start, dd, speed, back

    def reset_books(self, g: int, back: np.ndarray) -> None:
        idx = self.members[g]
        self.start_back[idx] = back
        self.overtakes[idx] = 0
        self.collisions[idx] = 0
        self.contact_sides[idx] = 0
        self.damage[idx] = 0.0
        self.impulse[idx] = 0.0
        self.gap_ahead[idx] = OPPONENT_RANGE_M
        prog = -back
        self.ahead[g] = prog[:, None] > prog[None, :]
        self.touching[idx, :] = False
        self.touching[:, idx] = False
        self.terms[:, idx] = 0.0

    # ------------------------------------------------------------------ acting
    def actions(self, core, learner_action: tuple[np.ndarray, np.ndarray, np.ndarray]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(steer, throttle, brake) ``[n]`` for every car: the learners' given, the opponents' from their drivers."""
        N, n = self.N, self.n
        steer, thr, brk = np.zeros(n), np.zeros(n), np.zeros(n)
        steer[:N], thr[:N], brk[:N] = learner_action
        if self.K == 0:
            return steer, thr, brk
        view = None
        sd: tuple[list, list] | None = None
        pol_rows: dict[str, list[int]] = {}
        for car in range(N, n):
            j = (car - N) % self.K
            ds = self.kinds[j]
            if ds.kind == "parked":
                brk[car] = 1.0
                continue
            if ds.kind == "policy":
                pol_rows.setdefault(ds.policy, []).append(car)
                continue
            if view is None:
                view = _TrackFrameFleet(core.fleet, core.car_origins())
                sd = (core.s.tolist(), core.d.tolist())
            steer[car], thr[car], brk[car] = self.drivers[car - N].act(view, car, self._side_room(core, car, sd))
            v_lim = self._follow_limit(core, car)
            v = float(core.fleet.vel_body[car, 0])
            if v > v_lim:  # a car close ahead on its line: no throttle, brake to its speed
                thr[car] = 0.0
                brk[car] = max(brk[car], min(1.0, (v - v_lim) / 5.0))
        for path, rows in pol_rows.items():
            # deferred: torch and tensordict, only for opponents driven by a network policy
            import torch
            from tensordict import TensorDict

            pol = self._policies[path]
            fresh = [i for i, c in enumerate(rows) if c in self._restarted]
            if fresh:
                pol.forget_rows(fresh)
                self._restarted.difference_update(rows[i] for i in fresh)
            obs = {k: torch.from_numpy(np.ascontiguousarray(core._obs_all[k][rows])) for k in pol.obs_keys}
            td = pol(TensorDict(obs, batch_size=[len(rows)]))
            a = td.get("action").numpy().astype(np.float64)
            a = np.clip(np.nan_to_num(a), -1.0, 1.0)
            steer[rows] = a[:, 0]
            if a.shape[1] == 2:
                thr[rows], brk[rows] = np.maximum(a[:, 1], 0.0), np.maximum(-a[:, 1], 0.0)
            else:
                thr[rows], brk[rows] = (a[:, 1] + 1) * 0.5, (a[:, 2] + 1) * 0.5
        return steer, thr, brk

    #: Scripted opponents keep ``FOLLOW_MIN_M + FOLLOW_HEADWAY_S x closing speed`` behind a car on their line
    FOLLOW_MIN_M, FOLLOW_HEADWAY_S, FOLLOW_WIDTH_M = 6.0, 1.0, 2.6

    #: A car counts as alongside while the along-track distance between the centres is under the car's length plus
    #: ``SIDE_OVERLAP_M`` (its nose is at least level with the other's rear bumper, less this margin) and it is at
    #: least ``SIDE_OFFSET_M`` to one side (a car straight behind is a following car, not one alongside); scripted
    #: opponents keep ``side_gap_m`` between centres from it and stay ``SIDE_EDGE_M`` inside the edges [m]
    SIDE_OVERLAP_M, SIDE_OFFSET_M, SIDE_EDGE_M = 2.0, 1.0, 1.2

    def _side_room(self, core, car: int, sd: tuple[list, list] | None = None) -> tuple[float, float] | None:
        """The lateral offsets [m] a scripted opponent may track: with a car alongside (see ``SIDE_OVERLAP_M``,
        ``SIDE_OFFSET_M``; within ``side_gap_m`` across it) it keeps ``side_gap_m`` between centres, staying on its side of that car,
        instead of turning in across it — the side-collision filter of TORCS's ``bt`` robot (``filterSColl``) in
        its simplest form. None when no car is alongside (or ``side_gap_m`` is 0): it tracks its line. ``sd``: the
        cars' track ``(s, d)`` as lists (read once per control step by :meth:`actions`)."""
        gap = self.spec.side_gap_m
        if gap <= 0.0:
            return None
        s, d = sd if sd is not None else (core.s.tolist(), core.d.tolist())
        tr = core.car_tracks[car]
        L = tr.length
        reach = self.params.length + self.SIDE_OVERLAP_M
        lo, hi = -math.inf, math.inf
        for o in self._members_of[car]:
            if o == car:
                continue
            ds = (s[o] - s[car] + 0.5 * L) % L - 0.5 * L
            dd = d[o] - d[car]
            if abs(ds) > reach or not self.SIDE_OFFSET_M <= abs(dd) < gap:
                continue
            if dd > 0.0:  # it is on our left: stay right of it
                hi = min(hi, d[o] - gap)
            else:
                lo = max(lo, d[o] + gap)
        if lo == -math.inf and hi == math.inf:
            return None
        wl, wr = (float(np.asarray(w).reshape(-1)[0]) for w in tr.width(s[car]))
        lo, hi = max(lo, -wr + self.SIDE_EDGE_M), min(hi, wl - self.SIDE_EDGE_M)
        if lo > hi:  # squeezed between two cars (or against the edge): the middle of the room there is
            lo = hi = 0.5 * (lo + hi)
        return lo, hi

    def _follow_limit(self, core, car: int) -> float:
        """The speed [m/s] a scripted opponent may drive at so as not to run into a car ahead of it on its line
        (within ``FOLLOW_WIDTH_M`` laterally): TORCS robots' collision avoidance in its simplest form."""
        g = int(self.group[car])
        L = core.car_tracks[car].length
        s, d, vx = core.s, core.d, core.fleet.vel_body[:, 0]
        lim = math.inf
        length = self.params.length
        for o in self.members[g].tolist():
            if o == car:
                continue
            ds = (s[o] - s[car]) % L
            if ds > 60.0 or abs(d[o] - d[car]) > self.FOLLOW_WIDTH_M:
                continue
            gap = ds - length
            lim = min(lim, max(float(vx[o]), 0.0) + (gap - self.FOLLOW_MIN_M) / self.FOLLOW_HEADWAY_S)
        return lim

    # ------------------------------------------------------------------ books
    def update(self, core, pair_impulse: np.ndarray) -> None:
        """Race books and the race reward terms after a control step (``pair_impulse [n, n]``: contact impulse
        between each pair of cars this step [N s])."""
        N, M = self.N, self.M
        members = self.members
        prog = core.dist_raced - self.start_back  # race progress from the race's start point [m]
        pg = prog[members]  # [N, M]
        ahead = pg[:, :, None] > pg[:, None, :]
        passed = ahead & ~self.ahead  # a now ahead of b, was not
        lost = ~ahead & self.ahead
        gained = passed.sum(axis=2) - lost.sum(axis=2)  # [N, M]
        self.overtakes[members] += gained
        self.ahead = ahead
        old_pos = self.race_pos.copy()
        self.race_pos[members] = 1 + ahead.sum(axis=1)  # 1 + cars ahead of it
        # gap to the nearest car ahead in the race (along the track) and to the follower
        diff = pg[:, None, :] - pg[:, :, None]  # [g, a, b]: how far b is ahead of a
        big = np.where(diff > 0, diff, np.inf)
        gap = big.min(axis=2)
        gap = np.minimum(gap, OPPONENT_RANGE_M)
        self.gap_ahead[members] = gap
        behind = np.where(diff < 0, -diff, np.inf)
        follower = behind.argmin(axis=2)
        follower_gap = behind.min(axis=2)
        # contacts
        imp = pair_impulse.sum(axis=1) / 1000.0  # [kN s]
        self.impulse = imp
        self.damage = self.damage + imp
        touch = pair_impulse > 0
        new = touch & ~self.touching
        self.collisions = self.collisions + new.sum(axis=1)
        if new.any():
            self._book_contact_sides(core, new)
        self.touching = touch
        # reward terms (per car): collision [kN s], positions gained, gap shortfall [-], blocking [m]
        v = core.fleet.vel_body[:, 0]
        safe = np.maximum(self.spec.safe_gap_min_m, self.spec.safe_headway_s * np.maximum(v, 0.0))
        gap_all = self.gap_ahead
        short = np.clip(1.0 - gap_all / safe, 0.0, 1.0)
        block = np.zeros(self.n)
        d = core.d
        d_prev = getattr(self, "_d_prev", d)
        for g in range(N):
            for a in range(M):
                if follower_gap[g, a] <= self.spec.block_range_m:
                    car, fol = members[g, a], members[g, follower[g, a]]
                    block[car] = max(0.0, abs(d_prev[car] - d[fol]) - abs(d[car] - d[fol]))
        self._d_prev = d.copy()
        self.terms = np.stack([imp, (old_pos - self.race_pos).astype(np.float64), short, block])

    #: Where the other car's centre was, along the car's heading, when a contact began: ``ahead`` more than half a car
    #: length in front of the car's centre (it ran into that car, or that car cut across its nose), ``behind`` more
    #: than half a length behind (hit from behind, or it cut back in across the car it passed), else ``alongside``.
    CONTACT_SIDES = ("ahead", "alongside", "behind")

    def _book_contact_sides(self, core, new: np.ndarray) -> None:
        """Count each contact begun this step (``new [n, n]``) by where the other car was (:attr:`CONTACT_SIDES`)."""
        pos, yaw = core.fleet.pos[:, :2], core.fleet.yaw
        half = 0.5 * float(self.params.length)
        for a, b in zip(*np.nonzero(new)):
            dx, dy = pos[b] - pos[a]
            x = math.cos(yaw[a]) * dx + math.sin(yaw[a]) * dy  # the other car's centre along car a's heading [m]
            self.contact_sides[a, 0 if x > half else 2 if x < -half else 1] += 1

    def info(self) -> dict[str, np.ndarray]:
        return {"racePos": self.race_pos.copy(), "overtakes": self.overtakes.copy(), "collisions": self.collisions.copy(),
                "damage": self.damage.copy(), "impulse": self.impulse.copy(), "gapAhead": self.gap_ahead.copy()}

    # ------------------------------------------------------------------ exact resume
    _BOOKS = ("start_back", "race_pos", "start_pos", "overtakes", "collisions", "contact_sides", "damage", "impulse",
              "gap_ahead", "ahead", "touching", "terms", "pace")

    def get_state(self) -> dict[str, Any]:
        drivers = [None if d is None else {"slip": float(d._slip), "chord": int(d._chord), "chord_front": int(d._chord_front),
                                           "v": np.asarray(d._v), "a": np.asarray(d._a), "track": d.track.name,
                                           "surface": d.track.default_surface}
                   for d in self.drivers]
        books = {k: np.array(getattr(self, k), copy=True) for k in self._BOOKS}
        books["d_prev"] = np.array(getattr(self, "_d_prev", np.zeros(self.n)), copy=True)
        return {"books": books, "drivers": drivers}

    def set_state(self, state: Mapping[str, Any], core) -> None:
        for k in self._BOOKS:
            if k == "contact_sides" and k not in state["books"]:  # a state saved before the book existed: none counted
                self.contact_sides = np.zeros((self.n, 3), dtype=np.int64)
                continue
            setattr(self, k, np.array(state["books"][k], copy=True))
        self._d_prev = np.array(state["books"]["d_prev"], copy=True)
        for i, d in enumerate(state["drivers"]):
            if d is None:
                self.drivers[i] = None
                continue
            car = self.N + i
            drv = self._driver(core.car_tracks[car], i % self.K, 1.0)
            drv._v, drv._a = np.asarray(d["v"]).tolist(), np.asarray(d["a"]).tolist()
            drv._slip, drv._chord, drv._chord_front = float(d["slip"]), int(d["chord"]), int(d["chord_front"])
            self.drivers[i] = drv


def load_opponent_policy(spec: str, loader: Callable[[str], Any] | None):
    """A frozen policy for opponents, ``loader(spec)``; its observation keys must be ones the env gives every car.
    :class:`TrafficError` (one line) when no loader is handed in, the loader fails (a ``ValueError``, as
    ``torcsrl.policies.PolicyError`` is) or the policy reads what an opponent cannot have."""
    if loader is None:
        raise TrafficError(f"traffic opponent policy {spec!r} needs a policy loader, which this env was not given; build it "
                           "with make_env(..., policy_loader=torcsrl.policies.load_policy) (or TrafficSpec.with_policy_loader)")
    try:
        pol = loader(spec)
    except ValueError as err:
        raise TrafficError(f"traffic opponent policy {spec!r}: {err}") from None
    bad = [k for k in pol.obs_keys if k not in OPPONENT_OBS_KEYS]
    if bad:
        raise TrafficError(f"traffic opponent policy {spec!r} reads {bad}, which the env cannot give an opponent; "
                           f"allowed: a policy on {', '.join(OPPONENT_OBS_KEYS)}")
    return pol
