"""Replay memory of the training loop: a ring of env steps in which every observation is stored ONCE.

Why not TorchRL's ``TensorDictReplayBuffer`` + ``MultiStepTransform``: with one env step per
update, their per-call bookkeeping (writer, sampler, ``"index"`` keys, the transform's
concatenations) cost ~0.3 ms per ``extend``, ~0.3 ms per ``sample`` and ~0.8 ms per n-step
``inv`` on the project's CPU — 10-15 % of a TD3 step — and every transition kept its next
observation, so pixel transitions took two frames. Here:

* **Layout.** The env's ``streams`` parallel trajectories (cars x worker processes) are written
  one env step at a time: step ``t`` of stream ``s`` is row ``t * streams + s`` (mod the ring
  size), so the same stream's next step is ``streams`` rows further on. A row holds the
  observation, the action, the reward and the end flags of one transition — no next
  observation. The next observation of row ``i`` is the observation of row ``i + streams``,
  except when the transition ended its episode (``done``): then the reset observation follows,
  and the true final observation (needed to bootstrap a time-limit truncation) goes to a
  *finals* table, with the row's ``"final"`` entry pointing at it (``-1`` otherwise).
  Writing step ``t`` also writes its next observations into the rows step ``t + 1`` will
  occupy, so the newest transitions are sampleable at once. Bytes per transition are those of
  one observation + action + reward + 3 flags + a 4-byte pointer, plus one observation per
  finished episode (:attr:`ReplayBuffer.bytes_per_transition`).
* **N-step returns** (D4PG) are formed when sampling, from the stored 1-step rows:
  ``R = sum_{k<=m} gamma^k r_{t+k}`` with the window ``m < n_steps`` cut at the first end of
  episode, the next observation and end flags those after step ``t + m``, and
  ``steps_to_next_obs = m + 1`` (the loss discounts with ``gamma ** steps_to_next_obs``) — what
  TorchRL's ``MultiStepTransform`` computes. A transition becomes sampleable once its window is
  complete (``n_steps - 1`` steps later). The stored rows do not depend on ``n_steps``, so a
  dumped buffer can be shared between algorithms.
* **Sampling** draws uniform (or prioritized, :class:`Priorities`) row numbers with the torch
  generator and gathers each stored tensor with ``index_select``; the batch is a TensorDict
  with the keys the losses read (obs, ``action``, ``("next", obs)``, ``("next", "reward")``,
  ``("next", "done"|"terminated"|"truncated")``, ``steps_to_next_obs`` for n > 1, ``index``
  and, when prioritized, ``priority_weight``).

* **Frame stacks** (``history={"pixels": K}``: the actor sees K frames stacked along channels,
  :class:`torcsrl.transforms.FrameStack`): a row keeps only the newest frame of its observation's
  stack (the last ``C = channels / K`` channels), and a sampled transition gathers the K - 1 frames
  before it from the same stream's rows ``streams`` apart, stopping at its episode's first row (the
  row after a ``done``, or the oldest row still in the ring) and repeating that frame, which is the
  stack the env gave the policy (``padding="same"``). The next observation's stack is the next row's,
  or (at an end of episode) the row's own stack shifted by the final frame. Stored rows and dumps do
  not depend on K: a folder written at K = 1 is sampled at any K.

Storage is RAM (``torch.empty``: pages are touched only as rows are written) or memory-mapped
files (``storage="disk"``). :meth:`ReplayBuffer.dumps`/:meth:`ReplayBuffer.loads` write/read a
folder (``meta.json`` + memory-mapped TensorDicts); a buffer with the same layout is restored
row for row (the exact-resume path), another capacity or ``n_steps`` gets the newest rows.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Sequence

import torch
from tensordict import TensorDict, TensorDictBase

from torcsrl.utils.faults import OutputError, file_digest

FORMAT = "torcsrl-replay"
VERSION = 1
FLAGS = ("done", "terminated", "truncated")


class Priorities:
    """Proportional prioritized sampling over the ring's rows (Schaul et al. 2016), pure torch.

    ``P(i) = p_i^alpha / sum_j p_j^alpha`` over the sampleable rows (the others hold priority 0);
    importance weights ``(N P(i))^-beta`` normalised by their maximum over the buffer; rows
    entering the sampleable window get the largest priority seen. O(rows) per sample
    (``torch.multinomial``). (TorchRL's ``PrioritizedSampler`` needs its C++ segment trees, whose
    extension does not load against torch 2.13 in the ``torchrl`` 0.14.1 wheel.)

    Args:
        rows: ring size.
        alpha: priority exponent [-] (0 = uniform).
        beta: importance-sampling exponent [-].
        eps: added to every updated priority so none is zero.
    """

    def __init__(self, rows: int, alpha: float = 0.6, beta: float = 0.4, eps: float = 1e-6):
        self.alpha, self.beta, self.eps = float(alpha), float(beta), float(eps)
        self.prio = torch.zeros(int(rows), dtype=torch.float64)
        self.max = 1.0

    def admit(self, rows: slice) -> None:
        self.prio[rows] = self.max

    def retire(self, rows: slice) -> None:
        self.prio[rows] = 0.0

    def sample(self, n: int, batch_size: int) -> tuple[torch.Tensor, torch.Tensor]:
        """(rows, importance weights) of ``batch_size`` draws; ``n`` sampleable rows."""
        p = self.prio.pow(self.alpha)
        probs = p / p.sum()
        index = torch.multinomial(probs, batch_size, replacement=True)
        w = (n * probs[index]).pow(-self.beta)
        w_max = (n * probs[probs > 0].min()).pow(-self.beta)
        return index, (w / w_max).to(torch.float32)

    def update(self, index: torch.Tensor, priority: torch.Tensor) -> None:
        pr = priority.detach().to("cpu", torch.float64).reshape(-1).abs() + self.eps  # the loss may run on a GPU (device=cuda)
        self.prio[index.reshape(-1).cpu()] = pr
        self.max = max(self.max, float(pr.max()))

    def state_dict(self) -> dict:
        return {"prio": self.prio.clone(), "max": self.max}

    def load_state_dict(self, state: dict) -> None:
        self.prio.copy_(state["prio"])
        self.max = float(state["max"])


def _empty_like_rows(td: TensorDictBase, rows: int) -> TensorDict:
    """A TensorDict of ``rows`` uninitialised rows shaped like one row of ``td`` (RAM pages untouched)."""
    return td.apply(lambda t: torch.empty((rows, *t.shape[1:]), dtype=t.dtype), batch_size=[rows])


class ReplayBuffer:
    """Ring of env steps; samples 1-step or n-step transitions (see the module docstring).

    Args:
        capacity: transitions kept (rounded up to a multiple of ``streams``).
        batch_size: transitions per :meth:`sample`.
        obs_keys: observation keys (stored once per row; next observations reconstructed).

    Keyword Args:
        streams: parallel trajectories per env step (cars x worker processes); every
            :meth:`extend` brings whole env steps of all of them.
        n_steps: n of the n-step returns (1 = plain transitions).
        gamma: discount per env step (n-step returns only).
        storage: ``"ram"`` or ``"disk"`` (memory-mapped files under ``path``).
        path: folder of the disk storage.
        prioritized: proportional prioritized sampling (:class:`Priorities`).
        alpha, beta: its exponents.
        priority_key: where the loss writes the per-sample priority (read by
            :meth:`update_tensordict_priority`).
        history: frames per stack of the stacked image keys (``{"pixels": K}``); each frame is stored once
            (see the module docstring). Keys with K = 1 are plain.
    """

    def __init__(self, capacity: int, batch_size: int, obs_keys: Sequence[str], *, streams: int = 1, n_steps: int = 1, gamma: float = 0.99,
                 storage: str = "ram", path: str | Path | None = None, prioritized: bool = False, alpha: float = 0.6, beta: float = 0.4,
                 priority_key: str = "td_error", extra_keys: Sequence[str] = (), history: dict[str, int] | None = None):
        if storage not in ("ram", "disk"):
            raise ValueError(f"unknown buffer.storage {storage!r}; known: ram, disk")
        if storage == "disk" and path is None:
            raise ValueError("buffer.storage=disk needs a folder (buffer.path)")
        if int(streams) < 1 or int(n_steps) < 1 or int(capacity) < 1:
            raise ValueError(f"capacity, streams and n_steps must be >= 1, got {capacity}, {streams}, {n_steps}")
        self.streams, self.n_steps, self.gamma = int(streams), int(n_steps), float(gamma)
        self.capacity = math.ceil(int(capacity) / self.streams) * self.streams
        self.batch_size = int(batch_size)
        self.obs_keys = list(obs_keys)
        self.extra_keys = list(extra_keys)
        self.history = {str(k): int(v) for k, v in (history or {}).items() if int(v) > 1}
        bad = [k for k in self.history if k not in self.obs_keys]
        if bad or any(v < 1 for v in (history or {}).values()):
            raise ValueError(f"replay: history {dict(history or {})} names keys {bad} it does not store or a stack below 1 frame; "
                             f"allowed: keys of {self.obs_keys} with integers >= 1")
        self._row_keys = ("action", *self.extra_keys, "reward", *FLAGS)
        self._done = 2 + len(self.extra_keys)  # where "done" sits in a step's non-observation tensors
        self.storage_kind, self.path = storage, None if path is None else Path(path)
        self.priority_key = priority_key
        self.lag = (self.n_steps - 1) * self.streams  # rows whose n-step window is still open
        self._offsets = torch.arange(self.n_steps) * self.streams  # rows of the same stream's next steps
        self._discounts = self.gamma ** torch.arange(self.n_steps, dtype=torch.float32)
        # ring rows: the kept transitions, the open windows, and one step of next observations
        self.rows = self.capacity + self.lag + self.streams
        self.written = 0  # rows written so far (row r lives at r % self.rows)
        self.finals_written = 0
        self._rows: TensorDict | None = None  # obs keys, action, reward, flags, final
        self._finals: TensorDict | None = None  # final observations of done rows
        self._leaves: list = []
        self.priorities = Priorities(self.rows, alpha, beta) if prioritized else None

    # ---- sizes ------------------------------------------------------------------------------
    def __len__(self) -> int:
        """Sampleable transitions."""
        return max(0, min(self.written - self.lag, self.capacity))

    @property
    def bytes_per_transition(self) -> int:
        """Bytes one stored row takes (the finals table adds one observation per finished episode)."""
        if self._rows is None:
            return 0
        return int(sum(t.element_size() * t[0].numel() for t in self._rows.values(True, True)))

    @property
    def bytes_per_final(self) -> int:
        """Bytes one final observation takes (one per finished episode)."""
        if self._finals is None:
            return 0
        return int(sum(t.element_size() * t[0].numel() for t in self._finals.values(True, True)))

    # ---- writing ----------------------------------------------------------------------------
    def _allocate(self, row: TensorDict, final: TensorDict) -> None:
        rows, finals = _empty_like_rows(row, self.rows), _empty_like_rows(final, self.rows)
        if self.storage_kind == "disk":
            try:
                self.path.mkdir(parents=True, exist_ok=True)
                rows = rows.memmap_like(prefix=str(self.path / "rows"))
                finals = finals.memmap_like(prefix=str(self.path / "finals"))
            except (OSError, RuntimeError) as err:  # tensordict raises RuntimeError when a file cannot be sized (full disk)
                reason = err.strerror if isinstance(err, OSError) and err.strerror else str(err).splitlines()[0][-120:]
                raise OutputError(f"buffer.path: cannot write the disk replay buffer in {self.path} ({reason}); allowed: a folder "
                                  "this user can write, on a disk with free space") from None
        self._rows, self._finals = rows, finals
        self._obs = [self._rows[k] for k in self.obs_keys]
        self._fin = [self._finals[k] for k in self.obs_keys]
        self._final = self._rows["final"]
        self._leaves = [self._rows[k] for k in self._row_keys]

    def extend(self, data: TensorDictBase) -> None:
        """Add whole env steps: ``data`` holds ``streams x T`` transitions, time on the last batch dim when
        ``T > 1`` (``[streams, T]``, ``[T]`` for one stream; one step may come as ``[streams]`` or ``[]``)."""
        n, nb = self.streams, data.batch_dims
        if data.numel() % n:
            raise ValueError(f"replay: got {data.numel()} transitions, not whole steps of {n} streams")
        steps = data.numel() // n
        nxt = data.get("next")
        get = [data.get(k) for k in self.obs_keys], [nxt.get(k) for k in self.obs_keys], \
            [data.get("action"), *(data.get(k) for k in self.extra_keys), *(nxt.get(k) for k in ("reward", *FLAGS))]
        # [streams, T, ...] views of every tensor (plain tensor ops: TensorDict reshapes cost ~0.1 ms each)
        obs, nobs, rest = ([x.reshape(n, steps, *x.shape[nb:]) for x in xs] for xs in get)
        if self.history:  # a stacked image keeps its newest frame only (the earlier ones are earlier rows)
            obs, nobs = ([self._newest(k, x) for k, x in zip(self.obs_keys, xs)] for xs in (obs, nobs))
        if self._rows is None:
            row = TensorDict({k: o[:, 0] for k, o in zip(self.obs_keys, obs)}, batch_size=[n])
            row.update({k: x[:, 0] for k, x in zip(self._row_keys, rest)})
            row.set("final", torch.full((n,), -1, dtype=torch.int32))
            self._allocate(row, TensorDict({k: o[:, 0] for k, o in zip(self.obs_keys, nobs)}, batch_size=[n]))
        for t in range(steps):
            self._write_step([o[:, t] for o in obs], [o[:, t] for o in nobs], [x[:, t] for x in rest])

    def _newest(self, key: str, x: torch.Tensor) -> torch.Tensor:
        """The newest frame ``[n, T, C, H, W]`` of a stacked observation ``[n, T, K*C, H, W]`` (``x`` itself when unstacked)."""
        k = self.history.get(key, 1)
        if k == 1:
            return x
        c = self._rows[key].shape[1] if self._rows is not None else x.shape[2] // k
        if x.ndim != 5 or x.shape[2] != k * c:
            raise ValueError(f"replay: {key} of shape {tuple(x.shape[2:])} is not a stack of {k} frames of {c} channels "
                             f"[{k * c}, H, W]; allowed: the observations of frame_stack={k}")
        return x[:, :, -c:]

    def _write_step(self, obs: list, nobs: list, rest: list) -> None:
        n = self.streams
        p = self.written % self.rows
        q = (p + n) % self.rows  # where the next step goes: its observations are our next observations
        for dst, o, no in zip(self._obs, obs, nobs):
            dst[p:p + n].copy_(o)
            dst[q:q + n].copy_(no)
        for dst, x in zip(self._leaves, rest):
            dst[p:p + n].copy_(x)
        final = self._final
        final[p:p + n] = -1
        done = rest[self._done].reshape(n)
        if bool(done.any()):
            idx = done.nonzero().squeeze(-1)
            slots = (self.finals_written + torch.arange(idx.numel())) % self.rows
            for dst, no in zip(self._fin, nobs):
                dst[slots] = no[idx]
            final[p + idx] = slots.to(torch.int32)
            self.finals_written += idx.numel()
        self.written += n
        if self.priorities is not None:
            newest = self.written - self.lag  # rows [newest - n, newest) just became sampleable
            if newest > 0:
                a = (newest - n) % self.rows
                self.priorities.admit(slice(a, a + n))
            old = self.written - self.lag - self.capacity  # rows [old - n, old) just left the window
            if old > 0:
                a = (old - n) % self.rows
                self.priorities.retire(slice(a, a + n))

    def end_episodes(self) -> None:
        """End every stream's running episode at the newest step written, as a time-limit truncation (``done`` and
        ``truncated``, not ``terminated``: its final observation goes to the finals table and is bootstrapped from).
        For a training loop that swaps its env (a curriculum stage): the next step written starts new episodes and is
        never taken for the next observation of the old ones. Streams whose newest step ended already are left alone."""
        if self._rows is None or self.written == 0:
            return
        n = self.streams
        p = (self.written - n) % self.rows  # the newest step's rows (a whole step never wraps: rows is a multiple of n)
        q = (p + n) % self.rows  # its next observations, written with it
        idx = (~self._rows["done"][p:p + n].reshape(n)).nonzero().squeeze(-1)
        if idx.numel() == 0:
            return
        slots = (self.finals_written + torch.arange(idx.numel())) % self.rows
        for dst, src in zip(self._fin, self._obs):
            dst[slots] = src[q + idx]
        self._final[p + idx] = slots.to(torch.int32)
        self.finals_written += idx.numel()
        for flag in ("done", "truncated"):
            self._rows[flag][p + idx] = True

    # ---- reading ----------------------------------------------------------------------------
    def _next_obs(self, rows: torch.Tensor, done: torch.Tensor) -> list[torch.Tensor]:
        """Observations after the transitions in ``rows`` (``done``: their episode ended there)."""
        succ = (rows + self.streams) % self.rows
        out = [self._stacked(k, o, succ) if k in self.history else o.index_select(0, succ) for k, o in zip(self.obs_keys, self._obs)]
        if bool(done.any()):
            sel = done.nonzero().squeeze(-1)
            slots = self._rows["final"].index_select(0, rows.index_select(0, sel)).long()
            for k, o, src, fin in zip(self.obs_keys, out, self._obs, self._fin):
                last = fin.index_select(0, slots)
                if k in self.history:  # the row's own stack, shifted by the final frame
                    last = torch.cat([self._stacked(k, src, rows.index_select(0, sel))[:, last.shape[1]:], last], 1)
                o[sel] = last
        return out

    def _stacked(self, key: str, frames: torch.Tensor, rows: torch.Tensor) -> torch.Tensor:
        """``[B, K*C, H, W]``: the frames of ``rows`` and of the K - 1 steps of the same stream before each, oldest first,
        the first frame of the episode repeated where the episode (or the ring's oldest intact row) starts later."""
        k, n, size = self.history[key], self.streams, self.rows
        base = max(0, self.written + n - size)  # logical number of the oldest row whose observation is intact
        logical = base + (rows - base % size) % size
        done = self._rows["done"].reshape(-1)
        cur, cur_l = rows, logical
        idx = [rows]
        alive = torch.ones_like(rows, dtype=torch.bool)
        for _ in range(k - 1):
            prev, prev_l = (cur - n) % size, cur_l - n
            alive = alive & (prev_l >= base) & ~done.index_select(0, prev)
            cur, cur_l = torch.where(alive, prev, cur), torch.where(alive, prev_l, cur_l)
            idx.append(cur)
        order = torch.stack(idx[::-1], 1)  # [B, K], oldest first
        out = frames.index_select(0, order.reshape(-1))
        return out.reshape(rows.numel(), k * frames.shape[1], *frames.shape[2:])

    def transitions(self, rows: torch.Tensor, successor: bool = True) -> TensorDict:
        """The (n-step) transitions starting at ring rows ``rows`` (a 1-D long tensor); ``successor=False``: the steps
        without ``next`` (its observations, reward and flags)."""
        st = self._rows
        out = {k: self._stacked(k, o, rows) if k in self.history else o.index_select(0, rows) for k, o in zip(self.obs_keys, self._obs)}
        out["action"] = st["action"].index_select(0, rows)
        for k in self.extra_keys:
            out[k] = st[k].index_select(0, rows)
        if not successor:
            return TensorDict({**out, "index": rows}, batch_size=[rows.numel()])
        if self.n_steps == 1:
            end = rows
            reward = st["reward"].index_select(0, rows)
            flags = {f: st[f].index_select(0, rows) for f in FLAGS}
            extra = {}
        else:  # the window t .. t + n - 1, cut after the first end of episode
            n = self.n_steps
            window = (rows.unsqueeze(1) + self._offsets) % self.rows  # [B, n]
            r = st["reward"][window].squeeze(-1)  # [B, n]
            ended = st["done"][window].squeeze(-1)
            inside = torch.cumprod(torch.cat([torch.ones_like(ended[:, :1]), ~ended[:, :-1]], 1).to(r.dtype), 1)  # step k counts
            steps = inside.sum(1, keepdim=True).to(torch.int64)  # m + 1
            reward = (r * inside * self._discounts).sum(1, keepdim=True)
            end = window.gather(1, steps - 1).squeeze(1)
            flags = {f: st[f].index_select(0, end) for f in FLAGS}
            extra = {"steps_to_next_obs": steps}
        nxt = dict(zip(self.obs_keys, self._next_obs(end, flags["done"].reshape(-1))))
        nxt.update(reward=reward, **flags)
        b = rows.numel()
        return TensorDict({**out, **extra, "index": rows, "next": TensorDict(nxt, batch_size=[b])}, batch_size=[b])

    def sample(self, batch_size: int | None = None, successor: bool = True) -> TensorDict:
        """A batch of transitions, uniform (or prioritized) over the sampleable ones; ``successor=False``: without
        ``next`` (the same rows from the same random draws: for losses that read only the step itself, e.g. imitation)."""
        b = int(batch_size or self.batch_size)
        n = len(self)
        if n == 0:
            raise RuntimeError("cannot sample from an empty replay buffer")
        if self.priorities is None:
            rows = (torch.randint(0, n, (b,)) + (self.written - self.lag - n)) % self.rows
            return self.transitions(rows, successor)
        rows, w = self.priorities.sample(n, b)
        td = self.transitions(rows, successor)
        td.set("priority_weight", w)
        return td

    def update_tensordict_priority(self, td: TensorDictBase) -> None:
        """Set the priorities of the sampled rows ``td["index"]`` to ``td[priority_key]``."""
        if self.priorities is not None:
            self.priorities.update(td.get("index"), td.get(self.priority_key))

    def __getitem__(self, index) -> TensorDict:
        """Transitions by position among the sampleable ones, oldest first (``buffer[:]``: all)."""
        pos = torch.arange(len(self))[index]
        return self.transitions(((pos.reshape(-1) + (self.written - self.lag - len(self))) % self.rows))

    # ---- persistence ------------------------------------------------------------------------
    def _meta(self) -> dict:
        return {"format": FORMAT, "version": VERSION, "capacity": self.capacity, "rows": self.rows, "streams": self.streams,
                "n_steps": self.n_steps, "written": self.written, "finals_written": self.finals_written, "obs_keys": self.obs_keys,
                "extra_keys": self.extra_keys,
                "priorities": None if self.priorities is None else self.priorities.max}

    def dumps(self, path: str | Path) -> None:
        """Write the buffer to the folder ``path`` (rows and finals actually used, memory-mapped)."""
        path = Path(path)
        path.mkdir(parents=True, exist_ok=True)
        if self._rows is not None:
            end = min(self.written + self.streams, self.rows)
            if self.written < end:  # the rows after the newest step (not wrapped yet) hold its next observations only: their
                for dst in self._leaves:  # other columns were never written (torch.empty); zeros keep a dump a function of
                    dst[self.written:end].zero_()  # the steps written (the same seed writes the same files)
                self._final[self.written:end] = -1
            self._rows[:end].memmap(prefix=str(path / "rows"), copy_existing=True)
            if self.finals_written:
                self._finals[: min(self.finals_written, self.rows)].memmap(prefix=str(path / "finals"), copy_existing=True)
        if self.priorities is not None:
            torch.save(self.priorities.state_dict(), path / "priorities.pt")
        sums = {str(f.relative_to(path)): {"bytes": f.stat().st_size, "sha256": file_digest(f)}
                for f in sorted(path.rglob("*")) if f.is_file() and f != path / "meta.json"}
        (path / "meta.json").write_text(json.dumps({**self._meta(), "checksums": sums}))

    @staticmethod
    def verify(path: str | Path) -> None:
        """Check the files of a dump against the sizes and SHA-256 checksums in its meta.json (dumps written before
        checksums existed pass unchecked); ValueError naming the first file that differs, before anything is read."""
        path = Path(path)
        try:
            meta = json.loads((path / "meta.json").read_text())
        except (OSError, ValueError):
            raise ValueError(f"{path} is not a replay buffer folder written by torcsrl (no readable meta.json)") from None
        for rel, want in (meta.get("checksums") or {}).items():
            f = path / rel
            if not f.is_file():
                raise ValueError(f"replay buffer file {f} is missing; allowed: a folder written whole by ReplayBuffer.dumps")
            size = f.stat().st_size
            if size != want["bytes"]:
                raise ValueError(f"replay buffer file {f} is {size} bytes, its checksum record says {want['bytes']} (truncated "
                                 "or extended); allowed: an intact dump (an older checkpoint's, or a fresh copy)")
            if file_digest(f) != want["sha256"]:
                raise ValueError(f"replay buffer file {f} does not match its SHA-256 checksum (bytes changed after it was "
                                 "written); allowed: an intact dump (an older checkpoint's, or a fresh copy)")

    def loads(self, path: str | Path, verified: bool = False) -> None:
        """Read a folder written by :meth:`dumps` (same layout: row for row; otherwise the newest rows), after checking its
        files against their checksums (:meth:`verify`; ``verified=True``: the caller did)."""
        path = Path(path)
        try:
            meta = json.loads((path / "meta.json").read_text())
        except (OSError, ValueError):
            raise ValueError(f"{path} is not a replay buffer folder written by torcsrl (no readable meta.json)") from None
        if meta.get("format") != FORMAT or meta.get("version") != VERSION:
            raise ValueError(f"{path} holds a {meta.get('format')} v{meta.get('version')} buffer; this torcsrl reads {FORMAT} v{VERSION}")
        if meta["streams"] != self.streams or meta["obs_keys"] != self.obs_keys:
            raise ValueError(f"replay buffer {path} has {meta['streams']} streams of {meta['obs_keys']}; this run has {self.streams} of {self.obs_keys}")
        if meta.get("extra_keys", []) != self.extra_keys:
            raise ValueError(f"replay buffer {path} stores extra keys {meta.get('extra_keys', [])}; this buffer has {self.extra_keys}")
        if meta["written"] == 0:
            return
        if not verified:
            self.verify(path)  # before load_memmap, which would zero-fill (and extend) a truncated file
        try:
            rows = TensorDict.load_memmap(str(path / "rows"))
            finals = TensorDict.load_memmap(str(path / "finals")) if meta["finals_written"] else None
        except Exception as err:  # noqa: BLE001 - a missing or damaged rows/ or finals/ folder, whatever tensordict raises
            raise ValueError(f"replay buffer {path} is incomplete: its rows/ or finals/ folder is missing or unreadable "
                             f"({type(err).__name__}); allowed: a folder written whole by ReplayBuffer.dumps") from None
        if self._rows is None:
            fin = finals[:1] if finals is not None else TensorDict({k: rows[k][:1] for k in self.obs_keys}, batch_size=[1])
            self._allocate(rows[:1], fin)
        prio = torch.load(path / "priorities.pt", weights_only=True) if (path / "priorities.pt").is_file() else None
        if meta["rows"] == self.rows:  # the same layout: restore row for row
            self._rows[: rows.shape[0]].update_(rows)
            if finals is not None:
                self._finals[: finals.shape[0]].update_(finals)
            self.written, self.finals_written = int(meta["written"]), int(meta["finals_written"])
            if self.priorities is not None:
                if prio is not None:
                    self.priorities.load_state_dict(prio)
                else:
                    self._admit_all()
            return
        # another capacity or n_steps: copy the newest whole steps (and the next observations after them)
        src_rows, w = int(meta["rows"]), int(meta["written"])
        keep = min(w, src_rows - self.streams, self.capacity + self.lag)
        logical = torch.arange(w - keep, w + self.streams)
        src = logical % src_rows
        data = rows[src]
        fin = data["final"].long()
        fin[keep:] = -1  # the next step's rows: only their observations were written
        has = fin >= 0
        new_fin = torch.full_like(fin, -1)
        if bool(has.any()):
            k = int(has.sum())
            new_fin[has] = torch.arange(k)
            self._finals[:k].update_(finals[fin[has]])
            self.finals_written = k
        else:
            self.finals_written = 0
        data.set("final", new_fin.to(torch.int32))
        self._rows[: logical.numel()].update_(data)
        self.written = keep
        if self.priorities is not None:
            self._admit_all()

    def _admit_all(self) -> None:
        self.priorities.prio.zero_()
        n = len(self)
        if n:
            first = self.written - self.lag - n
            pos = (torch.arange(first, first + n)) % self.rows
            self.priorities.prio[pos] = self.priorities.max
