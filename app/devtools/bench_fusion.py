"""Benchmarks of the fusion: ``compose`` (the display modes of one eye), ``fuse`` (a whole
stereo frame against a fixed-homography fusion) and ``fuse-accuracy`` (the mapping against the
simulator's exact one)."""

from __future__ import annotations

from trifuse.app.devtools.benchmark import benchmark, median_ms
from trifuse.fusion.compose import DISPLAY_MODES


@benchmark(
    "compose",
    "display composition of one 1280x960 eye per mode vs one cv2.addWeighted (ms per eye)",
    baselines=tuple((f"{m}_ms", "addweighted_ms") for m in DISPLAY_MODES),
    default_repeat=30,
)
def compose(repeat: int) -> dict[str, float]:
    """Medians over ``repeat`` calls of ``fusion.composer.Composer.compose`` per mode.

    Synthetic eye (seeded): a colour image with gradients and noise; a thermal image of
    290-310 K with a hot blob, NaN on the left 10 % and top 5 % (outside the thermal
    field of view) and a fallback block of 20 % of the pixels, ``mark_fallback`` on;
    span from ``auto_span`` of both eyes. ``<mode>_ms``: one eye in that mode (``blend``
    at opacity 0.6, ``edges`` at strength 1, ``threshold`` above, ``isotherm`` on grey
    with palette colours, ``pip`` half-size centred); ``addweighted_ms``: the baseline, a
    plain ``cv2.addWeighted`` of two prepared 1280x960x3 images into a preallocated
    buffer; ``palette_ms``: ``apply_palette`` alone; ``auto_span_ms``: the shared span
    of two eyes; ``stereo_blend_ms``: a whole stereo frame in blend mode (shared span,
    both eyes composed into the halves of one side-by-side buffer); ``anaglyph_ms``.
    """
    import cv2
    import numpy as np

    from trifuse.fusion.compose import DisplaySettings
    from trifuse.fusion.composer import Composer
    from trifuse.fusion.palettes import apply_palette
    from trifuse.fusion.span import auto_span, resolve_span
    from trifuse.fusion.stereo_pair import anaglyph, stereo_halves

    w, h = 1280, 960
    rng = np.random.default_rng(0)
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    color = np.empty((h, w, 3), np.uint8)
    for k in range(3):
        ramp = 60 + 120 * ((xx * (k + 1) / w + yy / h) % 1.0)
        color[..., k] = np.clip(ramp + rng.normal(0, 8, (h, w)), 0, 255)
    blob = 15 * np.exp(-((xx - 800) ** 2 + (yy - 400) ** 2) / (2 * 150**2))
    thermal = (290 + 10 * xx / w + blob + rng.normal(0, 0.1, (h, w))).astype(np.float32)
    thermal[:, : w // 10] = np.nan
    thermal[: h // 20] = np.nan
    thermal_r = thermal + np.float32(1.5)
    fallback = np.zeros((h, w), bool)
    fallback[600:900, 200:800] = True
    span = auto_span([thermal, thermal_r])

    out = np.empty((h, w, 3), np.uint8)
    pal = np.empty((h, w, 3), np.uint8)
    index = np.empty((h, w), np.uint8)
    apply_palette(thermal, span, "iron", out=pal, index_out=index)
    figures = {
        "addweighted_ms": median_ms(
            lambda _i: cv2.addWeighted(pal, 0.6, color, 0.4, 0.0, dst=out), repeat
        ),
        "palette_ms": median_ms(
            lambda _i: apply_palette(thermal, span, "iron", out=pal, index_out=index), repeat
        ),
    }
    composer = Composer(w, h)
    for mode in DISPLAY_MODES:
        settings = DisplaySettings(
            mode=mode, threshold_k=300.0, isotherm_k=(298.0, 302.0), mark_fallback=True
        )
        figures[f"{mode}_ms"] = median_ms(
            lambda _i, s=settings: composer.compose(color, thermal, fallback, s, span, out=out),
            repeat,
        )
    figures["auto_span_ms"] = median_ms(lambda _i: auto_span([thermal, thermal_r]), repeat)

    blend = DisplaySettings(mode="blend")
    right = Composer(w, h)
    sbs = np.empty((h, 2 * w, 3), np.uint8)
    left_half, right_half = stereo_halves(sbs)

    def stereo(_i: int) -> None:
        s = resolve_span(blend, [thermal, thermal_r])
        composer.compose(color, thermal, fallback, blend, s, out=left_half)
        right.compose(color, thermal_r, fallback, blend, s, out=right_half)

    figures["stereo_blend_ms"] = median_ms(stereo, repeat)
    ana = np.empty((h, w, 3), np.uint8)
    figures["anaglyph_ms"] = median_ms(lambda _i: anaglyph(left_half, right_half, ana), repeat)
    return figures


@benchmark(
    "fuse",
    "full-resolution stereo fusion per frame, per display mode, against a fixed-homography "
    "fusion (ms)",
    default_repeat=30,
)
def fuse(repeat: int) -> dict[str, float]:
    """Median time of one fused stereo frame (two 1280 x 960 eyes) of the inspection scene.

    ``<mode>_ms``: warp both thermal images into their colour cameras, one shared span,
    compose both eyes into the side-by-side buffer, with the depth mapping as it is (a TOF
    frame arrives less often than a colour frame). ``tof_update_ms``: recomputing both eyes'
    mappings from a new TOF frame. ``blend_tof_every_frame_ms``: blend with a new TOF frame
    for every stereo frame (the worst case). ``range_correction_ms``: the TOF range
    correction of one TOF frame (before its mapping update). ``homography_ms``: the naive
    fusion, one fixed homography per eye (3 m) through the same warp and blend: the
    baseline, and
    ``blend_ratio`` / ``blend_tof_every_frame_ratio`` against it.
    """
    import cv2
    import numpy as np

    from trifuse.app.sources.sim.inspection import InspectionScenario
    from trifuse.fusion.accuracy import fixed_depth_mapping
    from trifuse.fusion.compose import DisplaySettings
    from trifuse.fusion.composer import Composer
    from trifuse.fusion.span import resolve_span
    from trifuse.fusion.stereo import StereoFusion
    from trifuse.fusion.stereo_pair import stereo_halves

    scenario = InspectionScenario(seed=0)
    frames, _ = scenario.render(3.0)
    rig = scenario.rig
    eyes = ("left", "right")
    colors = {e: frames[rig.eyes[e].color].image for e in eyes}
    thermals = {e: frames[rig.eyes[e].thermal].image for e in eyes}
    distance = frames["tof"].distance_m
    fusion = StereoFusion(rig)
    fusion.update_depth(distance)

    settings = {
        "blend": DisplaySettings(mode="blend"),
        "edges": DisplaySettings(mode="edges"),
        "thermal": DisplaySettings(mode="thermal"),
        "threshold": DisplaySettings(mode="threshold", threshold_k=(300.0, 400.0)),
        "isotherm": DisplaySettings(mode="isotherm", isotherm_k=(305.0, 312.0)),
        "pip": DisplaySettings(mode="pip"),
        "color": DisplaySettings(mode="color"),
    }
    figures = {}
    for mode, s in settings.items():
        figures[f"{mode}_ms"] = median_ms(
            lambda _i, s=s: fusion.compose(colors, thermals, s), repeat
        )
    figures["tof_update_ms"] = median_ms(lambda _i: fusion.update_depth(distance), repeat)

    def every_frame(_i: int) -> None:
        fusion.update_depth(distance)
        fusion.compose(colors, thermals, settings["blend"])

    figures["blend_tof_every_frame_ms"] = median_ms(every_frame, repeat)

    # The TOF range correction (rig file ``range_correction``) on each TOF frame.
    from trifuse.calib.range_correction import RangeCorrection, offset_grid_shape

    w_t, h_t = rig["tof"].image_size
    correction = RangeCorrection(
        image_size=(w_t, h_t),
        distance_start_m=0.5,
        distance_step_m=0.15,
        distance_coeffs_m=np.linspace(0.03, -0.01, 40),
        offset_step_px=8,
        offset_nodes_m=np.full(offset_grid_shape(w_t, h_t, 8), 0.002),
        amplitude_ref=1500.0,
        amplitude_log_range=(-1.5, 1.5),
        amplitude_coeffs_m=(0.004, -0.001),
    )
    amplitude = frames["tof"].image
    out = np.empty_like(distance)
    figures["range_correction_ms"] = median_ms(
        lambda _i: correction.apply(distance, amplitude, out=out), repeat
    )

    # Baseline: a fixed homography per eye, warped and blended the same way.
    w, h = fusion.size
    maps = {}
    for e in eyes:
        m = fixed_depth_mapping(rig, rig.eyes[e].color, rig.eyes[e].thermal, 3.0)
        maps[e] = cv2.convertMaps(
            m[..., 0].astype(np.float32), m[..., 1].astype(np.float32), cv2.CV_32FC1
        )
    composers = {e: Composer(w, h) for e in eyes}
    warped = {e: np.empty((h, w), np.float32) for e in eyes}
    frame = np.zeros((h, 2 * w, 3), np.uint8)
    no_fallback = np.zeros((h, w), bool)

    def homography(_i: int) -> None:
        for e in eyes:
            cv2.remap(
                thermals[e],
                maps[e][0],
                maps[e][1],
                cv2.INTER_LINEAR,
                dst=warped[e],
                borderMode=cv2.BORDER_CONSTANT,
                borderValue=np.nan,
            )
        span = resolve_span(settings["blend"], list(warped.values()))
        for e, half in zip(eyes, stereo_halves(frame), strict=True):
            composers[e].compose(
                colors[e], warped[e], no_fallback, settings["blend"], span, out=half
            )

    figures["homography_ms"] = median_ms(homography, repeat)
    figures["blend_ratio"] = figures["blend_ms"] / figures["homography_ms"]
    figures["blend_tof_every_frame_ratio"] = (
        figures["blend_tof_every_frame_ms"] / figures["homography_ms"]
    )
    return figures


@benchmark(
    "fuse-accuracy",
    "fused mapping against the simulator's exact mapping per distance band, TOF as "
    "simulated and range-corrected, against one fixed homography (thermal px)",
    default_repeat=1,
)
def fuse_accuracy(repeat: int) -> dict[str, float]:
    """Median and 95th percentile of |mapped - exact| in thermal pixels per distance band,
    both eyes of the inspection scene at t = 0, 5, 10, 20 s, more than 16 colour pixels
    (two TOF pixels) from depth edges, where the exact point is visible to the thermal
    imager and inside the TOF's view, and the TOF gave depth (no fallback).

    ``raw_*``: the TOF with its simulated systematic range error (about 40 mm RMS);
    ``corrected_*``: that error removed, as a range calibration would (noise stays);
    ``homography_*``: one fixed homography per eye for an assumed 3 m.
    """
    import numpy as np

    from trifuse.app.sources.sim.inspection import InspectionScenario
    from trifuse.app.sources.sim.render import HeadModel
    from trifuse.app.sources.sim.tof_error import RangeErrorModel
    from trifuse.fusion.accuracy import (
        BANDS_M,
        band_errors,
        depth_edges,
        exact_mapping,
        fixed_depth_mapping,
    )
    from trifuse.fusion.mapping import ViewMapping

    no_error = RangeErrorModel(
        bias_m=0.0, wiggle=(), radial_m=0.0, border_m=0.0, pixel_sigma_m=0.0, amplitude_m=0.0
    )
    figures: dict[str, float] = {}
    for label, model in (("raw", None), ("corrected", HeadModel(range_error=no_error))):
        scenario = InspectionScenario(model=model, seed=0)
        rig = scenario.rig
        ours, naive = [], []
        for t_s in (0.0, 5.0, 10.0, 20.0):
            for eye in ("left", "right"):
                tgt, src = rig.eyes[eye].color, rig.eyes[eye].thermal
                frames, truth = scenario.render(t_s, [tgt, src, "tof"])
                m = ViewMapping(rig, tgt, src)
                m.update(frames["tof"].distance_m)
                exact = exact_mapping(rig, tgt, src, truth[tgt].range_m, truth[src].range_m)
                mask = ~depth_edges(exact.depth_m, 16) & m.visible & ~m.fallback
                ours.append(band_errors(np.stack([m.map_x, m.map_y], -1), exact, mask))
                if label == "raw":
                    naive.append(band_errors(fixed_depth_mapping(rig, tgt, src, 3.0), exact, mask))
        sets = [(label, ours)] + ([("homography", naive)] if naive else [])
        for name, results in sets:
            for k, (lo, hi) in enumerate(BANDS_M):
                rows = [r[k] for r in results if r[k].pixels]
                weights = [r.pixels for r in rows]
                key = f"{name}_{lo:g}-{hi:g}m"
                figures[f"{key}_median_px"] = float(
                    np.average([r.median_px for r in rows], weights=weights)
                )
                figures[f"{key}_p95_px"] = float(
                    np.average([r.p95_px for r in rows], weights=weights)
                )
                figures[f"{key}_pixels"] = float(sum(weights))
    return figures
