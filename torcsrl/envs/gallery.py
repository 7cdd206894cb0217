"""Gallery of camera views: ``python -m torcsrl.envs.gallery --out docs/img``.

Renders the camera (:mod:`torcsrl.envs.camera`) on several tracks and surfaces — a straight, a
hairpin entry, dirt, wet, ice — from the hood, chase and top-down mounts, with the car placed
directly on track poses (no driving). Writes one PNG per scene and mount
(``camera_<scene>_<mount>.png``, at ``--size`` pixels), the policy's-eye view at the observation
resolution (``camera_<scene>_hood<res>.png``, 84 px by default) and a composite
``camera_gallery.png`` (rows: scenes; columns: hood at the observation resolution, hood, chase,
top-down, hood depth) for the README.
"""

from __future__ import annotations

import argparse
import logging
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from torcsrl.utils.bullet import pybullet as p

from torcsrl.envs import tracks
from torcsrl.envs.camera import MOUNTS, Camera, setup_renderer
from torcsrl.envs.world import build_world

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Scene:
    """A camera placement: the car at arc length ``s`` [m], lateral offset ``d`` [m] on ``track``."""

    name: str
    track: str
    surface: str | None
    s: float
    d: float = 0.0
    yaw_offset_deg: float = 0.0
    other_car_ahead_m: float | None = None  # a second car this far ahead (same track: visible)


SCENES: tuple[Scene, ...] = (
    Scene("oval_straight", "oval", "asphalt", 80.0, d=-2.0, other_car_ahead_m=25.0),
    Scene("hairpins_entry", "hairpins", "asphalt", 148.0, d=-3.0),
    Scene("rallycross_dirt", "rallycross", None, 600.0, d=1.0),
    Scene("alpine_wet", "alpine", "wet", 1870.0, d=-1.5),
    Scene("esses_ice", "esses", "ice", 1330.0, d=1.5),
    Scene("kidney_gravel", "kidney", "gravel", 780.0, d=0.0),
)


def _car_fleet(client_id: int, n: int):
    """The vehicle module's cars if it is importable (so the chase and top views show a car)."""
    try:
        # deferred: optional here (the gallery draws without car bodies)
        from torcsrl.envs.vehicle import CarFleet, make_ground
    except Exception as err:  # pragma: no cover - the vehicle module is optional here
        log.warning("no car bodies in the gallery (%s)", err)
        return None, None
    ground = make_ground(client_id)
    return CarFleet(client_id, n), ground


def render_scene(scene: Scene, size: int, obs_size: int, renderer: str = "tiny") -> dict[str, np.ndarray]:
    """Images of one scene: ``{mount: rgb [H, W, 3]}`` plus ``"hood_obs"`` and ``"depth"``."""
    cid = p.connect(p.DIRECT)
    try:
        rend = setup_renderer(cid, renderer)
        track = tracks.load(scene.track, surface=scene.surface)
        n_cars = 2 if scene.other_car_ahead_m else 1
        fleet, ground = _car_fleet(cid, n_cars)
        world = build_world(cid, track, ground_body=ground)
        xy = track.to_world(scene.s, scene.d)
        yaw = float(track.heading(scene.s)) + np.radians(scene.yaw_offset_deg)
        z = 0.45  # [m] chassis centre-of-mass height at rest (default car)
        if fleet is not None:
            z = float(fleet.pos[0, 2])
            xys, yaws = [xy], [yaw]
            if scene.other_car_ahead_m:
                s2 = scene.s + scene.other_car_ahead_m
                xys.append(track.to_world(s2, -scene.d))
                yaws.append(float(track.heading(s2)))
            fleet.reset(np.arange(n_cars), np.array(xys), np.array(yaws))
        pose = ([xy[0], xy[1], z], yaw)
        out: dict[str, np.ndarray] = {}
        vehicle = fleet.params if fleet is not None else None
        for mount in MOUNTS:
            cam = Camera(cid, size, size, mount=mount, renderer=rend, worlds=[world], vehicle=vehicle)
            rgb, depth = cam.render(*pose)
            out[mount] = rgb.transpose(1, 2, 0)
            if mount == "hood":
                out["depth"] = depth[0]
        cam = Camera(cid, obs_size, obs_size, mount="hood", renderer=rend, worlds=[world], vehicle=vehicle)
        out["hood_obs"] = cam.render(*pose)[0].transpose(1, 2, 0)
        return out
    finally:
        p.disconnect(cid)


def depth_image(depth: np.ndarray, far: float = 300.0) -> np.ndarray:
    """Depth [m] as an RGB image (log scale, near = bright)."""
    v = 1.0 - np.log1p(np.clip(depth, 0.0, far)) / np.log1p(far)
    bgr = cv2.applyColorMap((v * 255).astype(np.uint8), cv2.COLORMAP_INFERNO)
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


def _label(img: np.ndarray, text: str) -> np.ndarray:
    bar = np.full((22, img.shape[1], 3), 255, dtype=np.uint8)
    cv2.putText(bar, text, (4, 16), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (20, 20, 20), 1, cv2.LINE_AA)
    return np.concatenate([bar, img], axis=0)


def _save(path: Path, rgb: np.ndarray) -> None:
    cv2.imwrite(str(path), cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2BGR))


def make_gallery(out_dir: str | Path, size: int = 256, obs_size: int = 84, tile: int = 192,
                 scenes: tuple[Scene, ...] = SCENES, renderer: str = "tiny") -> list[Path]:
    """Render every scene, write the PNGs into ``out_dir``; returns the paths written."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    written: list[Path] = []
    rows = []
    for sc in scenes:
        imgs = render_scene(sc, size, obs_size, renderer)
        for mount in MOUNTS:
            path = out_dir / f"camera_{sc.name}_{mount}.png"
            _save(path, imgs[mount])
            written.append(path)
        path = out_dir / f"camera_{sc.name}_hood{obs_size}.png"
        _save(path, imgs["hood_obs"])
        written.append(path)
        cells = [
            (cv2.resize(imgs["hood_obs"], (tile, tile), interpolation=cv2.INTER_NEAREST),
             f"{sc.name}: hood {obs_size}px"),
            (cv2.resize(imgs["hood"], (tile, tile), interpolation=cv2.INTER_AREA), "hood"),
            (cv2.resize(imgs["chase"], (tile, tile), interpolation=cv2.INTER_AREA), "chase"),
            (cv2.resize(imgs["top"], (tile, tile), interpolation=cv2.INTER_AREA), "top-down"),
            (cv2.resize(depth_image(imgs["depth"]), (tile, tile), interpolation=cv2.INTER_AREA), "hood depth"),
        ]
        pad = np.full((tile + 22, 4, 3), 255, dtype=np.uint8)
        row = []
        for img, text in cells:
            row += [_label(img, text), pad]
        rows.append(np.concatenate(row[:-1], axis=1))
        rows.append(np.full((4, rows[-1].shape[1], 3), 255, dtype=np.uint8))
    path = out_dir / "camera_gallery.png"
    _save(path, np.concatenate(rows[:-1], axis=0))
    written.append(path)
    return written


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="docs/img", help="output folder")
    parser.add_argument("--size", type=int, default=256, help="resolution of the per-mount images [px]")
    parser.add_argument("--obs-size", type=int, default=84, help="observation resolution shown in the gallery [px]")
    parser.add_argument("--renderer", default="tiny", choices=("auto", "tiny", "egl"))
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    for path in make_gallery(args.out, size=args.size, obs_size=args.obs_size, renderer=args.renderer):
        print(path)


if __name__ == "__main__":
    main()
