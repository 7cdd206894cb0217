"""The expert driver, the racing line, the speed profile and the physical lap-time limit."""

from __future__ import annotations

import math

import numpy as np
import pytest

from torcsrl.envs import surfaces, tracks
from torcsrl.envs.expert import drive, limit_lap_time, main, racing_line, speed_profile
from torcsrl.envs.track import Track
from torcsrl.envs.vehicle import VehicleParams

G = 9.81


def circle_track(radius: float = 100.0, half_width: float = 6.0, surface: str = "asphalt") -> Track:
    """A circular track driven anticlockwise (turning left), one sample per ~1 m."""
    m = int(2 * math.pi * radius)
    phi = np.linspace(0.0, 2 * math.pi, m, endpoint=False)
    xy = np.stack([radius * np.cos(phi), radius * np.sin(phi)], axis=1)
    return Track("circle", xy, half_width, half_width, surfaces.surface_id(surface), default_surface=surface)


@pytest.mark.parametrize("surface", ["asphalt", "dirt", "ice"])
def test_limit_lap_on_a_circle_matches_closed_form(surface):
    """Constant-radius lap: m v^2 / R = mu (m g + 0.5 rho ClA v^2), lap = 2 pi R / v."""
    prm = VehicleParams.load()
    track = circle_track(surface=surface)
    mu = surfaces.MU[surfaces.surface_id(surface)]
    q = 0.5 * prm.air_density * prm.lift_area

    def closed_form(r: float) -> float:
        return 2 * math.pi * r / math.sqrt(mu * prm.mass * G * r / (prm.mass - mu * q * r))

    line = racing_line(track)
    r_line = float(np.mean(np.hypot(*line.xy.T)))
    assert r_line == pytest.approx(100.0 + 6.0 - 2.2, abs=0.05)  # least curvature: the outer margin
    assert limit_lap_time(track, params=prm, line="racing") == pytest.approx(closed_form(r_line), rel=0.01)
    assert limit_lap_time(track, params=prm, line="centre") == pytest.approx(closed_form(100.0), rel=0.01)
    # on a circle the lap time grows like sqrt(R): the best candidate is the innermost line
    best = limit_lap_time(track, params=prm)
    assert closed_form(100.0 - 6.0 + 2.2) * 0.99 <= best <= closed_form(100.0) * 1.001


def test_speed_profile_respects_grip_and_power():
    prm = VehicleParams.load()
    track = tracks.load("hairpins")
    line = racing_line(track)
    v = speed_profile(line, prm)
    mu = line.mu
    # never faster than the cornering limit (with downforce)
    q_down = 0.5 * prm.air_density * prm.lift_area
    a_lat_max = mu * (G + q_down * v**2 / prm.mass)
    assert np.all(v**2 * np.abs(line.kappa) <= a_lat_max * (1 + 1e-9))
    # decelerations within grip + drag + rolling resistance; accelerations within grip and power
    v_next = np.roll(v, -1)
    accel = (v_next**2 - v**2) / (2 * line.ds)
    q_drag = 0.5 * prm.air_density * prm.drag_area
    resist = q_drag * v**2 / prm.mass + line.crr * G
    assert np.all(-accel <= a_lat_max + resist + 1e-6)
    assert np.all(accel <= np.minimum(a_lat_max, prm.max_wheel_power_w() / (prm.mass * np.maximum(v, 1.0))) + 1e-6)
    assert v.max() <= prm.top_gear_speed() + 1e-9
    assert v.min() > 5.0


def test_racing_line_stays_inside_and_is_straighter_than_the_centre():
    track = tracks.load("esses")
    rl, centre = racing_line(track, margin_m=2.0), racing_line(track, kind="centre")
    assert np.all(rl.d <= track.w_left - 2.0 + 1e-9) and np.all(rl.d >= -track.w_right + 2.0 - 1e-9)
    assert np.sum(rl.kappa**2 * rl.ds) < 0.7 * np.sum(centre.kappa**2 * centre.ds)
    with pytest.raises(ValueError, match="line must be one of racing, centre"):
        racing_line(track, kind="optimal")


def test_limit_is_slower_on_lower_grip():
    track = tracks.load("kidney")
    times = [limit_lap_time(track, surface=s) for s in ("asphalt", "dirt", "ice")]
    assert times[0] < times[1] < times[2]


@pytest.mark.parametrize("name,surface", [("hairpins", "dirt"), ("oval", "asphalt"), ("rallycross", None)])
def test_expert_completes_laps_without_leaving_the_track(name, surface):
    track = tracks.load(name, surface=surface)
    r = drive(track, laps=2)
    assert r.completed, f"{name}: {len(r.lap_times)} laps, max |d|/w = {r.max_offset_ratio:.2f}"
    assert r.max_offset_ratio < 1.0
    flying = r.lap_times[1]
    assert r.limit <= flying <= 1.5 * r.limit, f"flying lap {flying:.2f} s vs limit {r.limit:.2f} s"
    assert r.lap_times[0] > flying  # the first lap starts from rest


def test_cli_prints_laps_and_writes_a_plot(tmp_path, capsys):
    png = tmp_path / "kidney.png"
    assert main(["--track", "kidney", "--surface", "dirt", "--laps", "1", "--plot", str(png)]) == 0
    out = capsys.readouterr().out
    assert "lap  1:" in out and "physical limit" in out
    assert png.stat().st_size > 10_000
    with pytest.raises(ValueError, match="unknown track"):
        main(["--track", "nowhere", "--laps", "1"])
