"""A measurement snapshot (issue 35, ``GET /api/snapshot``): the fused pair and each eye's
temperatures as files a thermographer keeps, in one ZIP archive.

- ``fused.png``: the side-by-side picture the stream published last (BGR as PNG; ``fused.jpg``
  when the stream holds only its JPEG);
- ``apparent_left.png``, ``apparent_right.png``: what the imagers read on each eye's colour
  pixels, 16-bit PNG in centi-kelvin (0: no reading);
- ``object_left.png``, ``object_right.png``: the surfaces' temperatures by the measurement
  equation with the parameters in force (the regions' own surfaces where they have them) and
  the TOF's distance at every pixel, the same encoding;
- ``parameters.json``: the object parameters, regions and alarm rules, the pictures' stamps;
- ``regions.csv``: each region's reading (as ``trifuse measure``'s table).

Pure but for the arrays it is given; about 0.5 s of CPU for the default head on a slow host.
"""

from __future__ import annotations

import csv
import io
import json
import zipfile
from collections.abc import Mapping, Sequence
from typing import Any

import cv2
import numpy as np

from trifuse.app.recording.measure import READING_COLUMNS, reading_fields
from trifuse.fusion.measure import Measurement
from trifuse.fusion.regions import Region, surface_maps
from trifuse.fusion.spot import SpotFrame
from trifuse.fusion.thermography import ObjectParameters, object_temperature

CENTI_KELVIN_MAX = 65535
"""The largest value a 16-bit PNG holds: 655.35 K (a reading above it is clipped)."""


def centi_kelvin_png(kelvin: np.ndarray) -> bytes:
    """``kelvin`` (H, W; NaN: none) as a 16-bit PNG of centi-kelvin, 0 for no reading."""
    ck = np.nan_to_num(np.round(np.asarray(kelvin, np.float64) * 100.0), nan=0.0)
    ok, png = cv2.imencode(".png", np.clip(ck, 0, CENTI_KELVIN_MAX).astype(np.uint16))
    if not ok:
        raise RuntimeError("OpenCV could not encode a 16-bit PNG")
    return png.tobytes()


def object_map(
    frame: SpotFrame, eye: str, params: ObjectParameters, regions: Sequence[Region]
) -> tuple[np.ndarray, np.ndarray]:
    """(apparent, object) temperatures (H, W) float64 kelvin of ``eye``'s whole picture."""
    w, h = frame.size
    ys, xs = np.divmod(np.arange(w * h), w)
    apparent, distance = frame.samples(eye, xs, ys)
    eps, refl = surface_maps(regions, eye, w, h, params.emissivity, params.reflected_k)
    corrected = object_temperature(
        apparent, distance, params, emissivity=eps.ravel(), reflected_k=refl.ravel()
    )
    return apparent.reshape(h, w), corrected.reshape(h, w)


TABLE_COLUMNS = ("stamp_ns", "region", *READING_COLUMNS)
"""``regions.csv``'s columns: ``trifuse measure``'s without time and alarms."""


def _table(stamp_ns: int, readings: Mapping[str, Measurement]) -> str:
    buf = io.StringIO()
    out = csv.DictWriter(buf, TABLE_COLUMNS, lineterminator="\n")
    out.writeheader()
    for name, m in readings.items():
        out.writerow({"stamp_ns": stamp_ns, "region": name, **reading_fields(m)})
    return buf.getvalue()


def snapshot_zip(
    frame: SpotFrame,
    fused_bgr: np.ndarray | None,
    fused_jpeg: bytes | None,
    fused_meta: Mapping[str, Any],
    params: ObjectParameters,
    regions: Sequence[Region],
    settings: Mapping[str, Any],
    readings: Mapping[str, Measurement],
) -> bytes:
    """The archive of the module's docstring. ``frame``: the spot meter's capture of the
    last picture; ``fused_*``: the stream's last picture (BGR or JPEG) and its metadata;
    ``settings``: the measurement settings (JSON-able); ``readings``: the regions read on
    ``frame``."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_STORED) as z:  # PNGs are compressed already
        if fused_bgr is not None:
            ok, png = cv2.imencode(".png", fused_bgr)
            if not ok:
                raise RuntimeError("OpenCV could not encode the fused picture as PNG")
            z.writestr("fused.png", png.tobytes())
        elif fused_jpeg is not None:
            z.writestr("fused.jpg", fused_jpeg)
        for eye in frame.eyes:
            apparent, corrected = object_map(frame, eye, params, regions)
            z.writestr(f"apparent_{eye}.png", centi_kelvin_png(apparent))
            z.writestr(f"object_{eye}.png", centi_kelvin_png(corrected))
        info = {
            "stamp_ns": frame.stamp_ns,
            "fused_stamp_ns": fused_meta.get("stamp_ns"),
            "encoding": "16-bit PNG, centi-kelvin, 0 = no reading",
            **settings,
        }
        z.writestr("parameters.json", json.dumps(info, indent=2, sort_keys=True))
        z.writestr("regions.csv", _table(frame.stamp_ns, readings))
    return buf.getvalue()
