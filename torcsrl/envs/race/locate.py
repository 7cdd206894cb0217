"""Where each car of a :class:`~torcsrl.envs.race.core.RaceCore` is: its Frenet position on its track (arc length
``s``, offset ``d``, ``trackPos``, angle to the track axis, the centreline chord it is on) and the surface under
each wheel, by exact projection.

Up to :data:`SCALAR_LOCATE_MAX_CARS` cars each point is followed chord by chord from the car's previous chord
(:meth:`Track.track_point`; in plain Python up to :data:`PYTHON_WALK_MAX_CARS` cars, else the same walk vectorised
over the cars, :meth:`Track.track_points`); beyond, or where a walk fails, one windowed vectorised projection per
track. :class:`CarLocator` is a mixin of the core: its methods read the fleet and write the core's position books.
"""

from __future__ import annotations

import math

import numpy as np

from torcsrl.envs import surfaces as _surf

__all__ = ["CarLocator", "SCALAR_LOCATE_MAX_CARS", "PYTHON_WALK_MAX_CARS"]

#: Up to this many cars, cars are followed along their tracks chord by chord (the exact walk of
#: :meth:`Track.track_point`); beyond, located by the windowed vectorised projection.
SCALAR_LOCATE_MAX_CARS = 8
#: Up to this many cars the walk runs car by car in plain Python; beyond, vectorised over the cars
#: (:meth:`Track.track_points`, the same numbers).
PYTHON_WALK_MAX_CARS = 4


class CarLocator:
    """The car-locating methods of :class:`~torcsrl.envs.race.core.RaceCore`."""

    #: Cars followed one by one in plain Python up to this many (an instance may raise it: the batched
    #: evaluation does, so that each car is located exactly as a one-car env locates it).
    scalar_locate_max_cars: int = SCALAR_LOCATE_MAX_CARS

    def _locate(self, idx_reset: np.ndarray | None = None) -> None:
        """Frenet position of every car and the surface under each wheel (exact projection).

        Few cars: each point is followed chord by chord from the car's previous chord in plain
        Python (a few µs). Many cars: one vectorised projection per track, windowed around the
        previous arc length.
        """
        fleet = self.fleet
        origin = self.car_origins()  # [N, 2]
        pos = fleet.pos[:, :2] - origin  # in each car's track frame
        wheels = fleet.wheel_xy - origin[:, None, :]  # [N, 4, 2]
        if self.n <= self.scalar_locate_max_cars:
            walk = self._locate_scalar if self.n <= PYTHON_WALK_MAX_CARS else self._locate_walk
            ids = walk(pos, wheels, fleet.yaw)
            if ids is not None:
                fleet._update_wheel_surfaces(ids)
                return
        pts = np.concatenate([pos[:, None, :], wheels], axis=1)  # [N, 5, 2]
        hint = self.s
        ids = np.empty((self.n, 4), dtype=np.int64)
        groups = [np.arange(self.n)] if self.n == 1 else [np.flatnonzero([t is u for t in self.car_tracks])
                                                            for u in {id(t): t for t in self.car_tracks}.values()]
        for g in groups:
            t = self.car_tracks[g[0]]
            s, d = t.project(pts[g], s_hint=np.repeat(hint[g, None], 5, axis=1), window_m=8.0)
            wl, wr, heading, sid = t.lookup(s)
            on = (d[:, 1:] <= wl[:, 1:]) & (d[:, 1:] >= -wr[:, 1:])
            ids[g] = np.where(on, sid[:, 1:], _surf.GRASS_ID)
            self.s[g] = s[:, 0]
            self.d[g] = d[:, 0]
            self.track_pos[g] = np.where(d[:, 0] >= 0.0, d[:, 0] / wl[:, 0], d[:, 0] / wr[:, 0])
            self.angle[g] = (fleet.yaw[g] - heading[:, 0] + math.pi) % (2.0 * math.pi) - math.pi
            self.chord[g] = t._locate(s[:, 0])[0]
        fleet._update_wheel_surfaces(ids)

    def _locate_scalar(self, pos: np.ndarray, wheels: np.ndarray, yaw: np.ndarray) -> np.ndarray | None:
        ids = []
        wl_ = wheels.tolist()
        for i in range(self.n):
            t = self.car_tracks[i]
            r = t.track_point(float(pos[i, 0]), float(pos[i, 1]), int(self.chord[i]))
            if r is None:
                return None
            s, d, chord, u = r
            wl, wr, heading, _ = t.frame_at(chord, u)
            self.s[i], self.d[i], self.chord[i] = s, d, chord
            self.track_pos[i] = d / wl if d >= 0.0 else d / wr
            self.angle[i] = (float(yaw[i]) - heading + math.pi) % (2.0 * math.pi) - math.pi
            sids = t.surfaces_at(wl_[i], chord)
            if sids is None:
                return None
            ids.append(sids)
        return np.array(ids, dtype=np.int64)

    def _locate_walk(self, pos: np.ndarray, wheels: np.ndarray, yaw: np.ndarray) -> np.ndarray | None:
        """:meth:`_locate_scalar` vectorised over the cars (:meth:`Track.track_points`): the same numbers, bit for
        bit, and the same side effects when a walk fails (the cars before the first failing one, and that car's own
        point if it settled, are written; then ``None``)."""
        n = self.n
        s_new, d_new, tp_new, ang_new = np.zeros(n), np.zeros(n), np.zeros(n), np.zeros(n)
        ch_new = np.zeros(n, dtype=np.int64)
        car_ok = np.zeros(n, dtype=bool)
        all_ok = np.zeros(n, dtype=bool)
        ids = np.empty((n, 4), dtype=np.int64)
        tracks = self.car_tracks
        first = tracks[0]
        groups = [np.arange(n)] if all(t is first for t in tracks) else \
            [np.flatnonzero([t is u for t in tracks]) for u in {id(t): t for t in tracks}.values()]
        pi, two_pi = math.pi, 2.0 * math.pi
        for g in groups:
            t = tracks[g[0]]
            tab = t._walk_table()
            wl_, dwl = t.w_left, t._delta(t.w_left)
            wr_, dwr = t.w_right, t._delta(t.w_right)
            s, d, ch, u, ok = t.track_points(pos[g, 0], pos[g, 1], self.chord[g])
            row = tab[ch]
            nx = row[:, 4] + u * row[:, 6]
            ny = row[:, 5] + u * row[:, 7]
            heading = np.fromiter(map(math.atan2, (-nx).tolist(), ny.tolist()), dtype=np.float64, count=len(g))
            wl = wl_[ch] + u * dwl[ch]
            wr = wr_[ch] + u * dwr[ch]
            with np.errstate(divide="ignore", invalid="ignore"):
                tp = np.where(d >= 0.0, d / wl, d / wr)
            s_new[g], d_new[g], ch_new[g], tp_new[g] = s, d, ch, tp
            ang_new[g] = (yaw[g] - heading + pi) % two_pi - pi
            car_ok[g] = ok
            # the wheels walk from their car's chord
            rs, rd, rc, ru, rok = t.track_points(wheels[g, :, 0], wheels[g, :, 1], np.repeat(ch, 4))
            w_l = wl_[rc] + ru * dwl[rc]
            w_r = wr_[rc] + ru * dwr[rc]
            ids[g] = np.where((-w_r <= rd) & (rd <= w_l), t.surface_ids[rc], _surf.GRASS_ID).reshape(-1, 4)
            all_ok[g] = ok & rok.reshape(-1, 4).all(axis=1)
        if all_ok.all():
            self.s[:], self.d[:], self.chord[:], self.track_pos[:], self.angle[:] = s_new, d_new, ch_new, tp_new, ang_new
            return ids
        f = int(np.argmin(all_ok))  # the first car whose walk failed: the scalar loop wrote the cars before it
        w = np.arange(n) < f
        w[f] = car_ok[f]
        for a, v in ((self.s, s_new), (self.d, d_new), (self.chord, ch_new), (self.track_pos, tp_new), (self.angle, ang_new)):
            a[w] = v[w]
        return None
