"""Compare the frames of benchmarks/gpu/egl_frames.py: tiny vs egl; write a PNG (tiny | egl | |diff|) and a JSON.

    python benchmarks/gpu/egl_compare.py OUTDIR
"""

from __future__ import annotations

import json
import os
import sys

import cv2
import numpy as np

SCALE = 4
SHOW = ("96x64", "84x84")


def grey(rgb: np.ndarray) -> np.ndarray:
    """[3, H, W] uint8 -> [H, W] float grey levels (ITU-R 601 luma)."""
    r, g, b = rgb.astype(np.float64)
    return 0.299 * r + 0.587 * g + 0.114 * b


def tile(rgb_hw3: np.ndarray, label: str, width: int) -> np.ndarray:
    img = cv2.resize(rgb_hw3, None, fx=SCALE, fy=SCALE, interpolation=cv2.INTER_NEAREST)
    h, w = img.shape[:2]
    canvas = np.full((h + 22, width, 3), 255, np.uint8)
    canvas[22:22 + h, :w] = img
    cv2.putText(canvas, label, (4, 16), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
    return canvas


def main(outdir: str) -> int:
    res: dict = {}
    rows = []
    width = max(int(k.split("x")[0]) for k in SHOW) * SCALE + 8
    for tag in ("", "_car"):
        ft, fe = (os.path.join(outdir, f"frames_{r}{tag}.npz") for r in ("tiny", "egl"))
        if not (os.path.exists(ft) and os.path.exists(fe)):
            print(f"compare{tag or ' world'}: missing {[f for f in (ft, fe) if not os.path.exists(f)]}")
            continue
        t, e = np.load(ft), np.load(fe)
        for k in sorted({n[4:] for n in t.files if n.startswith("rgb_")}):
            rt, re_ = t[f"rgb_{k}"], e[f"rgb_{k}"]
            dt, de = t[f"depth_{k}"], e[f"depth_{k}"]
            d_rgb = np.abs(rt.astype(np.int16) - re_.astype(np.int16))
            d_grey = np.abs(grey(rt) - grey(re_))
            rel = np.abs(dt - de) / np.maximum(dt, 1e-6)
            drawn = (dt < dt.max() - 1e-3) | (de < de.max() - 1e-3)
            entry = {
                "mean_abs_diff_grey": float(d_grey.mean()),
                "mean_abs_diff_rgb": float(d_rgb.mean()),
                "p99_abs_diff_grey": float(np.percentile(d_grey, 99)),
                "frac_px_grey_diff_gt_16": float((d_grey > 16).mean()),
                "depth_rel_diff_median": float(np.median(rel)),
                "depth_rel_diff_p95": float(np.percentile(rel, 95)),
                "frac_px_depth_rel_diff_gt_0.5pct": float((rel > 0.005).mean()),
                "frac_px_drawn_by_renderer_not_far": float(drawn.mean()),
                "mean_grey_tiny": float(grey(rt).mean()),
                "mean_grey_egl": float(grey(re_).mean()),
            }
            res[f"{'world' if not tag else 'car_ahead'}_{k}"] = entry
            print(f"compare {'world' if not tag else 'car ahead'} {k}: mean |grey diff| {entry['mean_abs_diff_grey']:.2f}, "
                  f"mean |rgb diff| {entry['mean_abs_diff_rgb']:.2f}, p99 {entry['p99_abs_diff_grey']:.1f}, "
                  f">16 levels {100 * entry['frac_px_grey_diff_gt_16']:.1f}% px; depth rel diff median "
                  f"{entry['depth_rel_diff_median']:.2e} p95 {entry['depth_rel_diff_p95']:.2e}")
            if k in SHOW:
                a, b = rt.transpose(1, 2, 0), re_.transpose(1, 2, 0)
                diff = d_rgb.transpose(1, 2, 0).astype(np.uint8)
                name = "world" if not tag else "car ahead"
                rows.append(np.concatenate([
                    tile(a, f"tiny {k} {name}", width), tile(b, f"egl {k} {name}", width),
                    tile(diff, f"|tiny-egl| (mean grey {entry['mean_abs_diff_grey']:.1f})", width),
                    tile(np.minimum(diff.astype(np.int32) * 4, 255).astype(np.uint8), "|tiny-egl| x4", width)], axis=1))
    if rows:
        w = max(r.shape[1] for r in rows)
        img = np.concatenate([np.pad(r, ((0, 4), (0, w - r.shape[1]), (0, 0)), constant_values=255) for r in rows], 0)
        cv2.imwrite(os.path.join(outdir, "egl_vs_tiny.png"), cv2.cvtColor(img, cv2.COLOR_RGB2BGR))
        print(f"wrote {os.path.join(outdir, 'egl_vs_tiny.png')} ({img.shape[1]}x{img.shape[0]})")
    with open(os.path.join(outdir, "egl_compare.json"), "w") as f:
        json.dump(res, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1]))
