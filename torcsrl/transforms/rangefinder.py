"""Rangefinder degradations: the 19-beam TORCS-style track sensor, metres, R_max = 200 m.

Every transform here works on ``x`` [*B, ..., D] (D beams, any D) and

* leaves an off-track scan (all beams < 0: the env writes -1) exactly as it is;
* keeps readings in [0, max_range]; "no return" is the sentinel ``max_range``
  (what the sensor reports when nothing is within range).

Severity ladders are the catalogue's (``docs/guides/degradation-catalogue.md``). Beam angles, when a
transform needs them (fov_loss, spray), default to D beams evenly spread over ±90° (TORCS's
default layout); pass ``beam_angles=[...]`` (degrees, left < 0) for another layout.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from ._base import CPU, Degradation

_F32 = np.float32
_ZERO, _ONE, _TINY = _F32(0.0), _F32(1.0), _F32(1e-12)


def _addcmul(x: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``x + a * b`` rounded once, as ``torch.addcmul`` does (a fused multiply-add; NumPy rounds twice)."""
    return torch.addcmul(torch.from_numpy(x), torch.from_numpy(a), torch.from_numpy(b)).numpy()


__all__ = [
    "BeamDegradation",
    "BeamNoise",
    "BeamQuantize",
    "BeamDropout",
    "DeadBeams",
    "FovLoss",
    "BeamBiasScale",
    "StuckBeams",
    "BeamOutliers",
    "BeamFog",
    "BeamRain",
    "BeamSnow",
    "BeamSpray",
    "OpponentNoise",
    "OpponentDropout",
]


class BeamDegradation(Degradation):
    """Base of the rangefinder degradations: off-track scans pass through; output in [0, R]."""

    sensor = "rangefinder"
    default_in_keys = ("rangefinder",)
    options = {"max_range": 200.0}

    def _check_options(self):
        if not float(self.opts["max_range"]) > 0:
            raise ValueError(f"{type(self).__name__}: max_range must be > 0")
        self.R = float(self.opts["max_range"])
        self._R32 = _F32(self.R)

    def _check_spec(self, key, spec):
        if not spec.dtype.is_floating_point or len(spec.shape) < 1:
            raise TypeError(
                f"{type(self).__name__}: {key!r} must be a float vector of ranges [..., D], got "
                f"{spec.dtype} {tuple(spec.shape)}"
            )

    def _degrade(self, x, key, st, reset):
        if x.ndim == 1 and x.is_cpu and x.dtype == torch.float32:  # one env, one scan: the fused path
            xn = x.numpy()
            if self._fused and reset is None:
                y = torch.from_numpy(self._beams_np(xn, key, st))
            else:
                y = self._beams(x, key, st, reset, 0)
            return x if xn[0] < 0 else y  # an off-track scan (every beam at -1) passes; y is drawn all the same
        y = self._beams(x, key, st, reset, len(st["_B"]))
        # an off-track scan has every beam at -1, a valid one none below 0: one beam tells
        return torch.where(x[..., :1] < 0, x, y)

    #: has :meth:`_beams_np`, the one-env step in NumPy (same draws, same float32 results)
    _fused = False

    def _beams_np(self, x: np.ndarray, key, st: dict) -> np.ndarray:
        """One env's step on a float32 scan ``x [D]`` (no reset): what :meth:`_beams` computes, with
        NumPy float32 arithmetic on the same draws (each op rounds as torch's does; the log is torch's).
        At one env a torch op costs more in dispatch than its 19 floats; these cost a fraction."""
        raise NotImplementedError

    @staticmethod
    def _p(st: dict, name: str) -> np.float32:
        """The one env's parameter ``name`` as a NumPy float32 (cached until the next episode draw)."""
        c = st.get("_np")
        if c is None:
            c = st["_np"] = {}
        v = c.get(name)
        if v is None:
            v = c[name] = _F32(st[name].item())
        return v

    def _u(self, D: int) -> np.ndarray:
        return self.rand((D,), CPU).numpy()

    def _n(self, D: int) -> np.ndarray:
        return self.randn((D,), CPU).numpy()

    def _episode_mask(self, x, key, st, reset, nb, make) -> torch.Tensor:
        """A per-episode bool mask [*B, ..., D] from ``make(x)``, kept until the env resets."""
        kst = st["_keys"].get(key)
        if kst is None or kst["mask"].shape != x.shape:
            kst = st["_keys"][key] = {"mask": make(x)}
        elif reset is not None:
            kst["mask"] = torch.where(self.bview(reset, x, nb), make(x), kst["mask"])
        return kst["mask"]

    def _beams(self, x, key, st, reset, nb):
        raise NotImplementedError

    def _angles(self, D: int, device) -> torch.Tensor:
        a = self.opts.get("beam_angles")
        if a is None:
            return torch.linspace(-90.0, 90.0, D, device=device)
        a = torch.as_tensor(a, dtype=torch.float32, device=device)
        if a.numel() != D:
            raise ValueError(
                f"{type(self).__name__}: beam_angles has {a.numel()} entries for {D} beams"
            )
        return a


# ------------------------------------------------------------------------ step noise
class BeamNoise(BeamDegradation):
    """``rangefinder.noise``: r + N(0, a + b·r), drawn every step."""

    name = "rangefinder.noise"
    ladder = {"a": (0.02, 0.05, 0.10, 0.20, 0.50), "b": (0.005, 0.01, 0.02, 0.03, 0.05)}

    def _beams(self, x, key, st, reset, nb):
        sigma = self.bview(st["a"], x, nb) + self.bview(st["b"], x, nb) * x
        return torch.addcmul(x, self.randn(x.shape, x.device), sigma).clamp_(0.0, self.R)

    _fused = True

    def _beams_np(self, x, key, st):
        sigma = self._p(st, "a") + self._p(st, "b") * x
        return np.minimum(np.maximum(_addcmul(x, self._n(x.shape[0]), sigma), _ZERO), self._R32)


class BeamQuantize(BeamDegradation):
    """``rangefinder.quantize``: round to a step Δ (0.01 .. 0.5 m). Deterministic."""

    name = "rangefinder.quantize"
    ladder = {"step": (0.01, 0.05, 0.1, 0.25, 0.5)}
    kinds = {"step": "pos"}
    stochastic = False

    def _beams(self, x, key, st, reset, nb):
        d = self.bview(st["step"], x, nb)
        return (torch.round(x / d) * d).clamp_(0.0, self.R)

    _fused = True

    def _beams_np(self, x, key, st):
        d = self._p(st, "step")
        return np.minimum(np.maximum(np.round(x / d) * d, _ZERO), self._R32)


class BeamDropout(BeamDegradation):
    """``rangefinder.dropout``: each beam, each step, has no return with probability p
    (→ the ``max_range`` sentinel)."""

    name = "rangefinder.dropout"
    ladder = {"p": (0.02, 0.05, 0.10, 0.20, 0.35)}
    kinds = {"p": "prob"}

    def _beams(self, x, key, st, reset, nb):
        drop = self.rand(x.shape, x.device) < self.bview(st["p"], x, nb)
        return x.masked_fill(drop, self.R)

    _fused = True

    def _beams_np(self, x, key, st):
        return np.where(self._u(x.shape[0]) < self._p(st, "p"), self._R32, x)


class BeamOutliers(BeamDegradation):
    """``rangefinder.outliers``: crosstalk; with probability p a beam reads U(0, R_max)."""

    name = "rangefinder.outliers"
    ladder = {"p": (0.004, 0.008, 0.012, 0.016, 0.020)}
    kinds = {"p": "prob"}

    def _beams(self, x, key, st, reset, nb):
        u = self.rand(x.shape, x.device)
        p = self.bview(st["p"], x, nb)
        hit = u < p
        return torch.where(hit, u / p.clamp_min(1e-12) * self.R, x)

    _fused = True

    def _beams_np(self, x, key, st):
        u = self._u(x.shape[0])
        p = self._p(st, "p")
        hit = u < p
        if not np.count_nonzero(hit):
            return x.copy()
        return np.where(hit, u / max(p, _TINY) * self._R32, x)


# ------------------------------------------------------------------------ episode faults
class DeadBeams(BeamDegradation):
    """``rangefinder.dead_beams``: k contiguous beams blocked for the whole episode (k = 1, 2,
    3, 5, 7), at a random place redrawn at each reset. A blocked beam reads ``dead_value``
    (default: the no-return sentinel max_range)."""

    name = "rangefinder.dead_beams"
    ladder = {"k": (1, 2, 3, 5, 7)}
    kinds = {"k": "int"}
    options = {"max_range": 200.0, "dead_value": None}
    episodic = True

    def _draw_faults(self, p, B, device):
        return {"start_u": self.rand(B, device)}

    def _beams(self, x, key, st, reset, nb):
        def make(x):
            D = x.shape[-1]
            k = st["k"].clamp(max=D)
            start = (st["start_u"] * (D - k + 1)).floor()
            ar = torch.arange(D, device=x.device, dtype=x.dtype)
            s = self.bview(start, x, nb)
            return ((ar >= s) & (ar < s + self.bview(k, x, nb))).expand(x.shape)

        dead = self._episode_mask(x, key, st, reset, nb, make)
        v = self.opts["dead_value"]
        return x.masked_fill(dead, self.R if v is None else float(v))

    def dead_mask(self, D: int) -> torch.Tensor:
        """The current episode's dead beams per env, [*B, D] (for tests and plots)."""
        st = self._state
        k = st["k"].clamp(max=D)
        start = (st["start_u"] * (D - k + 1)).floor().unsqueeze(-1)
        ar = torch.arange(D, device=k.device)
        return (ar >= start) & (ar < start + k.unsqueeze(-1))


class FovLoss(BeamDegradation):
    """``rangefinder.fov_loss``: beams outside ±``kept`` degrees are dead (no return).
    kept = 80, 70, 60, 45, 30°. Deterministic for a given severity."""

    name = "rangefinder.fov_loss"
    ladder = {"kept": (80.0, 70.0, 60.0, 45.0, 30.0)}
    options = {"max_range": 200.0, "beam_angles": None}
    stochastic = False
    episodic = True

    def _beams(self, x, key, st, reset, nb):
        def make(x):
            ang = self._angles(x.shape[-1], x.device).abs()
            return (ang > self.bview(st["kept"], x, nb) + 1e-4).expand(x.shape)

        return x.masked_fill(self._episode_mask(x, key, st, reset, nb, make), self.R)


class BeamBiasScale(BeamDegradation):
    """``rangefinder.bias_scale``: miscalibration, (1 + ε)·r + b_i with ε ~ U(±E) per env and
    b_i ~ U(±bias) per beam, drawn at each reset. bias = .1, .25, .5, 1, 2 m;
    eps = .5, 1, 2, 3, 5 %."""

    name = "rangefinder.bias_scale"
    ladder = {"bias": (0.1, 0.25, 0.5, 1.0, 2.0), "eps": (0.005, 0.01, 0.02, 0.03, 0.05)}
    episodic = True

    def _draw_faults(self, p, B, device):
        return {"eps_draw": (self.rand(B, device) * 2 - 1) * p["eps"]}

    def _beams(self, x, key, st, reset, nb):
        kst = st["_keys"].get(key)
        if kst is None or kst["u"].shape != x.shape:
            kst = st["_keys"][key] = {"u": self.rand(x.shape, x.device) * 2 - 1}
        elif reset is not None:
            new = self.rand(x.shape, x.device) * 2 - 1
            kst["u"] = torch.where(self.bview(reset, x, nb), new, kst["u"])
        bias = kst["u"] * self.bview(st["bias"], x, nb)
        scale = 1.0 + self.bview(st["eps_draw"], x, nb)
        return torch.addcmul(bias, scale, x).clamp_(0.0, self.R)


class StuckBeams(BeamDegradation):
    """``rangefinder.stuck``: k beams (1, 1, 2, 3, 4) freeze at their reading from a random onset
    step ~ U{0..onset_max} (default 100 steps = 2 s) until the episode ends."""

    name = "rangefinder.stuck"
    ladder = {"k": (1, 1, 2, 3, 4)}
    kinds = {"k": "int"}
    options = {"max_range": 200.0, "onset_max": 100}
    temporal = True
    episodic = True

    def _check_options(self):
        super()._check_options()
        if int(self.opts["onset_max"]) < 0:
            raise ValueError("StuckBeams: onset_max must be >= 0")

    def _draw_faults(self, p, B, device):
        onset = self.randint(0, int(self.opts["onset_max"]) + 1, B, device)
        return {"onset": onset, "t": torch.zeros(B, dtype=torch.long, device=device)}

    def _begin_step(self, st, reset):
        if reset is None:
            st["t"] = st["t"] + 1

    def _beams(self, x, key, st, reset, nb):
        kst = st["_keys"].get(key)
        fresh = kst is None or kst["frozen"].shape != x.shape
        if fresh or reset is not None:
            u = self.rand(x.shape, x.device)
            rank = u.argsort(-1).argsort(-1)
            stuck = rank < self.bview(st["k"], x, nb)
            if fresh:
                kst = st["_keys"][key] = {"stuck": stuck, "frozen": x.clone()}
            else:
                kst["stuck"] = torch.where(self.bview(reset, x, nb), stuck, kst["stuck"])
        capture = self.bview(st["t"] == st["onset"], x, nb)
        if reset is not None:
            capture = capture & self.bview(reset, x, nb)
        kst["frozen"] = torch.where(capture, x, kst["frozen"])
        active = self.bview(st["t"] >= st["onset"], x, nb) & kst["stuck"]
        return torch.where(active, kst["frozen"], x)


# ------------------------------------------------------------------------ weather
def _r_eff(alpha: torch.Tensor, tau: float) -> torch.Tensor:
    return math.log(1.0 / tau) / (2.0 * alpha.clamp_min(1e-9))


class BeamFog(BeamDegradation):
    """``rangefinder.fog``: two-way extinction e^(-2αr) below the detection threshold τ = 0.01
    beyond R_eff = ln(1/τ)/(2α) → no return; near false returns (backscatter) at r ~ Exp(5 m)
    with probability p_spurious per beam per step.

    α = 0.005, 0.01, 0.02, 0.03, 0.06 /m (R_eff = 460, 230, 115, 77, 38 m).
    """

    name = "rangefinder.fog"
    ladder = {
        "alpha": (0.005, 0.01, 0.02, 0.03, 0.06),
        "p_spurious": (0.005, 0.01, 0.02, 0.04, 0.08),
    }
    kinds = {"alpha": "pos", "p_spurious": "prob"}
    options = {"max_range": 200.0, "tau": 0.01, "spurious_scale": 5.0}

    def _check_options(self):
        super()._check_options()
        if not 0 < float(self.opts["tau"]) < 1:
            raise ValueError("BeamFog: tau must be in (0, 1)")

    def _draw_faults(self, p, B, device):
        return {"r_eff": _r_eff(p["alpha"], float(self.opts["tau"])), "inv_p": 1.0 / p["p_spurious"].clamp_min(1e-12)}

    def _beams(self, x, key, st, reset, nb):
        y = x.masked_fill(x > self.bview(st["r_eff"], x, nb), self.R)
        u = self.rand(x.shape, x.device)
        v = (u * self.bview(st["inv_p"], x, nb)).clamp_(1e-12, 1.0)  # U(0, 1) given a hit
        near = v.log_().mul_(-float(self.opts["spurious_scale"]))  # Exp(scale)
        return torch.where(u < self.bview(st["p_spurious"], x, nb), torch.minimum(y, near), y)

    _fused = True

    def _beams_np(self, x, key, st):
        y = np.where(x > self._p(st, "r_eff"), self._R32, x)
        u = self._u(x.shape[0])
        hit = u < self._p(st, "p_spurious")
        if not np.count_nonzero(hit):  # no false return this step (the common case): nothing else to compute
            return y
        v = torch.from_numpy(np.minimum(np.maximum(u * self._p(st, "inv_p"), _TINY), _ONE)).log_().numpy()  # torch's log
        near = v * _F32(-float(self.opts["spurious_scale"]))
        return np.where(hit, np.minimum(y, near), y)


class BeamRain(BeamDegradation):
    """``rangefinder.rain``: range noise ×m of the s1 noise model (a = 2 cm, b = 0.5 %), beam
    dropout, and near spurious returns (drops) at r ~ Exp(3 m)."""

    name = "rangefinder.rain"
    ladder = {
        "noise_mult": (1.5, 2.0, 3.0, 4.0, 6.0),
        "p_drop": (0.01, 0.02, 0.04, 0.08, 0.15),
        "p_spurious": (0.002, 0.005, 0.01, 0.02, 0.04),
    }
    kinds = {"p_drop": "prob", "p_spurious": "prob"}
    options = {"max_range": 200.0, "base_a": 0.02, "base_b": 0.005, "spurious_scale": 3.0}

    def _beams(self, x, key, st, reset, nb):
        m = self.bview(st["noise_mult"], x, nb)
        sigma = m * (float(self.opts["base_a"]) + float(self.opts["base_b"]) * x)
        y = torch.addcmul(x, self.randn(x.shape, x.device), sigma).clamp_(0.0, self.R)
        u = self.rand(x.shape, x.device)
        pd = self.bview(st["p_drop"], x, nb)
        ps = self.bview(st["p_spurious"], x, nb)
        y = y.masked_fill(u < pd, self.R)
        v = ((u - pd) / ps.clamp_min(1e-12)).clamp_min(1e-12)
        near = -torch.log(v) * float(self.opts["spurious_scale"])
        spur = (u >= pd) & (u < pd + ps)
        return torch.where(spur, torch.minimum(y, near), y)

    _fused = True

    def _beams_np(self, x, key, st):
        D = x.shape[0]
        m = self._p(st, "noise_mult")
        sigma = m * (_F32(float(self.opts["base_a"])) + _F32(float(self.opts["base_b"])) * x)
        y = np.minimum(np.maximum(_addcmul(x, self._n(D), sigma), _ZERO), self._R32)
        u = self._u(D)
        pd, ps = self._p(st, "p_drop"), self._p(st, "p_spurious")
        y = np.where(u < pd, self._R32, y)
        spur = (u >= pd) & (u < pd + ps)
        if not np.count_nonzero(spur):
            return y
        v = np.maximum((u - pd) / max(ps, _TINY), _F32(1e-12))
        near = -torch.log(torch.from_numpy(v)).numpy() * _F32(float(self.opts["spurious_scale"]))
        return np.where(spur, np.minimum(y, near), y)


class BeamSnow(BeamDegradation):
    """``rangefinder.snow``: flake returns at r ~ U(1, 15 m) with probability p_flake per beam
    per step, plus fog (α = 0.003, 0.006, 0.012, 0.02, 0.03 /m: falling snow attenuates less
    than fog of the same severity)."""

    name = "rangefinder.snow"
    ladder = {
        "p_flake": (0.01, 0.03, 0.06, 0.10, 0.15),
        "alpha": (0.003, 0.006, 0.012, 0.02, 0.03),
    }
    kinds = {"p_flake": "prob", "alpha": "pos"}
    options = {"max_range": 200.0, "tau": 0.01, "flake_min": 1.0, "flake_max": 15.0}

    def _draw_faults(self, p, B, device):
        return {"r_eff": _r_eff(p["alpha"], float(self.opts["tau"])), "inv_p": 1.0 / p["p_flake"].clamp_min(1e-12)}

    def _beams(self, x, key, st, reset, nb):
        y = x.masked_fill(x > self.bview(st["r_eff"], x, nb), self.R)
        u = self.rand(x.shape, x.device)
        lo, hi = float(self.opts["flake_min"]), float(self.opts["flake_max"])
        flake = (u * self.bview(st["inv_p"], x, nb)).mul_(hi - lo).add_(lo)
        return torch.where(u < self.bview(st["p_flake"], x, nb), torch.minimum(y, flake), y)

    _fused = True

    def _beams_np(self, x, key, st):
        y = np.where(x > self._p(st, "r_eff"), self._R32, x)
        u = self._u(x.shape[0])
        hit = u < self._p(st, "p_flake")
        if not np.count_nonzero(hit):
            return y
        lo, hi = float(self.opts["flake_min"]), float(self.opts["flake_max"])
        flake = u * self._p(st, "inv_p") * _F32(hi - lo) + _F32(lo)
        return np.where(hit, np.minimum(y, flake), y)


class BeamSpray(BeamDegradation):
    """``rangefinder.spray``: a car ahead throws spray; beams that would hit it (within
    ``range`` = 30 m) return near the spray instead, with probability p per beam per step.

    The sensor does not see other cars, so "beams that hit a car" is the forward cone
    |angle| <= ``cone`` (30°): the case of a car ahead. The return is U(2 m, 30 m).
    """

    name = "rangefinder.spray"
    ladder = {"p": (0.05, 0.10, 0.20, 0.30, 0.40)}
    kinds = {"p": "prob"}
    options = {"max_range": 200.0, "beam_angles": None, "cone": 30.0, "range": 30.0}

    def _beams(self, x, key, st, reset, nb):
        def make(x):
            return (self._angles(x.shape[-1], x.device).abs() <= float(self.opts["cone"])).expand(x.shape)

        cone = self._episode_mask(x, key, st, reset, nb, make)
        u = self.rand(x.shape, x.device)
        p = self.bview(st["p"], x, nb)
        r = 2.0 + (float(self.opts["range"]) - 2.0) * (u / p.clamp_min(1e-12))
        return torch.where((u < p) & cone, torch.minimum(x, r), x)

    _fused = True

    def _beams_np(self, x, key, st):
        kst = st["_keys"].get(key)
        if kst is None or kst["mask"].shape != x.shape:  # no episode mask yet for this key: the torch path makes it
            return self._beams(torch.from_numpy(x), key, st, None, 0).numpy()
        cone = kst["mask"].numpy()
        u = self._u(x.shape[0])
        p = self._p(st, "p")
        hit = (u < p) & cone
        if not np.count_nonzero(hit):
            return x.copy()
        r = _F32(2.0) + _F32(float(self.opts["range"]) - 2.0) * (u / max(p, _TINY))
        return np.where(hit, np.minimum(x, r), x)


# ------------------------------------------------------------------------ the opponents sensor
class _OpponentSectors:
    """Mixin: the 36-sector ``opponents`` sensor (TORCS SCR; [m], 200 = free sector) reuses the beam transforms on the
    sectors that see a car; a free sector stays free (the sensor reports no phantom car out of noise)."""

    sensor = "opponents"
    default_in_keys = ("opponents",)

    def _beams(self, x, key, st, reset, nb):
        return torch.where(x < self.R, super()._beams(x, key, st, reset, nb), x)

    def _beams_np(self, x, key, st):
        return np.where(x < self._R32, super()._beams_np(x, key, st), x)


class OpponentNoise(_OpponentSectors, BeamNoise):
    """``opponents.noise``: d + N(0, a + b·d) on the sectors that see a car (the rangefinder's ladder)."""

    name = "opponents.noise"


class OpponentDropout(_OpponentSectors, BeamDropout):
    """``opponents.dropout``: a sector that sees a car misses it with probability p (reads free, 200 m)."""

    name = "opponents.dropout"
