"""Skyline detection on the real Puy de Sancy 360-degree photo; writes docs/puydesancy_overlay.png.

Run: .venv/bin/python bench/vision_puydesancy.py   (needs ../shared/data beside the repository)
The overlay is a downscaled, colour-quantised crop around the horizon, for the operator's eye.
"""

from __future__ import annotations

import datetime
import os
import sys
import time
from pathlib import Path

import cv2
import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from appliance.atomic import write_bytes_atomic  # noqa: E402
from appliance.vision.panorama import load_panorama  # noqa: E402
from appliance.vision.skyline_detect import DetectionConfig, detect_columns, draw_overlay, resample  # noqa: E402
from bench.results_file import append_result, checkout_commit  # noqa: E402

PHOTO = REPO.parent / "shared" / "data" / "panorama" / "puydesancy_equirect_4096x2048.jpg"
OUT = REPO / "docs" / "puydesancy_overlay.png"
RESULTS = REPO / "bench" / "results" / "vision_puydesancy.md"
HEADER = "# Skyline detection on the Puy de Sancy photo\n\nOverlay: docs/puydesancy_overlay.png (checked by eye).\n"


def main() -> int:
    if not PHOTO.is_file():
        print(f"{PHOTO} is absent; nothing to do")
        return 0
    pano = load_panorama(PHOTO)
    cfg = DetectionConfig(min_elevation_deg=-30.0, max_elevation_deg=30.0)
    t0 = time.perf_counter()
    cols = detect_columns(pano, cfg)
    dt = time.perf_counter() - t0
    sky = resample(cols, pano, 1.0)
    ov = draw_overlay(pano, cols, thickness_px=4)
    top, bot = int(pano.elevation_to_row(20.0)), int(pano.elevation_to_row(-20.0))
    crop = ov[top:bot]
    small = cv2.resize(crop, (crop.shape[1] * 2 // 5, crop.shape[0] * 2 // 5), interpolation=cv2.INTER_AREA)
    # two halves stacked keep the picture readable; quantising the colours keeps the PNG small
    half = small.shape[1] // 2
    stacked = np.vstack([small[:, :half], small[:, half : 2 * half]])
    stacked = (stacked // 16) * 16 + 8
    OUT.parent.mkdir(exist_ok=True)
    ok, buf = cv2.imencode(".png", stacked, [cv2.IMWRITE_PNG_COMPRESSION, 9])
    if not ok:
        return 1
    write_bytes_atomic(OUT, buf.tobytes())
    valid = float(np.isfinite(cols.row).mean())
    print(
        f"detection {dt * 1000:.0f} ms on {pano.width}x{pano.height}; columns valid {valid:.1%};"
        f" 1-degree rows valid {sky.valid.sum()}/360; overlay {OUT} ({len(buf) // 1024} kB)"
    )
    rows_header = ("| date | commit | detection time, 4096x2048 (el -30..30) | columns with a skyline |"
                   " 1-degree rows with a skyline | load |\n|---|---|---|---|---|---|\n")
    existing = RESULTS.read_text(encoding="utf-8") if RESULTS.is_file() else ""
    row = (f"| {datetime.date.today()} | {checkout_commit(REPO)} | {dt * 1000:.0f} ms | {valid:.1%} |"
           f" {int(sky.valid.sum())}/360 | {os.getloadavg()[0]:.1f} |\n")
    # each run adds its row (the notes under earlier rows stay); the table's header once
    append_result(RESULTS, HEADER + "\n" + rows_header,
                  row if rows_header in existing else ("\n" + rows_header + row if existing else row))
    return 0


if __name__ == "__main__":
    sys.exit(main())
