"""Benchmark of the display's AGC (issue 19, :mod:`fusion.agc`): ``trifuse bench --only agc``.

On the simulated inspection room with its hot pipe in view: how many palette levels the
fused picture uses (entropy of the palette index), whether each person stands apart from
the wall (the difference of their median palette positions), and what a stereo frame
costs, per AGC mode, against today's linear blend measured in the same run.
"""

from __future__ import annotations

from trifuse.app.devtools.benchmark import benchmark, median_ms

AGC_TIMES_S = (0.0, 27.0)
"""Frames measured: the head looking straight ahead and 12 degrees to the left; the
people and the pipe are in view in both."""
MIN_PIXELS = 500
"""A person (or the wall) with fewer fused pixels in a frame is not measured there."""
MAX_GAIN_SWEEP = (6.0, 8.0, 10.0, 11.0, 12.0, 13.0, 15.0, 20.0, 1000.0)
"""Maximum gains (palette steps per kelvin) measured in ``plateau`` besides the default
(1000: in effect no cap)."""


def _groups(names: list[str]) -> tuple[dict[str, list[int]], list[int], list[int]]:
    """Solid indices of each person (names ``person*``, grouped by the part before the first
    ``_``: ``person_body`` and ``person_head`` are ``person``), of the walls
    (``wall*``) and of the hot pipe (``hot_pipe``)."""
    people: dict[str, list[int]] = {}
    for i, name in enumerate(names):
        if name.startswith("person"):
            people.setdefault(name.split("_", 1)[0], []).append(i)
    walls = [i for i, n in enumerate(names) if n.startswith("wall")]
    pipe = [i for i, n in enumerate(names) if n == "hot_pipe"]
    return people, walls, pipe


@benchmark(
    "agc",
    "AGC modes on the inspection room: entropy of the palette index (bits), person/wall "
    "separation (share of the palette), stereo blend per mode vs linear (ms)",
    baselines=(("plateau_blend_ms", "linear_blend_ms"), ("dde_blend_ms", "linear_blend_ms")),
    default_repeat=10,
)
def agc(repeat: int) -> dict[str, float]:
    """Per AGC mode (``linear``, ``plateau``, ``dde``), over the frames at
    :data:`AGC_TIMES_S` of the inspection room (accurate render, imagers as simulated: no
    balance applied), both eyes' fused pixels (a thermal reading on the colour pixel)
    pooled, each frame's own table (no smoothing):

    - ``<mode>_entropy_bits``: Shannon entropy of the palette index, mean over the frames
      (8 bits: all 256 entries equally used);
    - ``<mode>_separation_<person>``: (median palette index of the person's pixels - that
      of the walls') / 255, the smallest over the frames; ``<mode>_separation``: the
      smallest over the people (the simulator's per-pixel solid ids tell the pixels apart:
      solids ``person*``, grouped by name, and ``wall*``);
    - ``<mode>_offset_steps``: median palette index of the left eye's walls - the right
      eye's, the largest over the frames: the simulated imagers' 1.5 K disagreement in
      palette steps (the same walls, different colours in the two eyes);
    - ``plateau_g<max_gain>_{entropy_bits,separation,offset_steps}``: the same for
      ``plateau`` at each maximum gain of :data:`MAX_GAIN_SWEEP` (the default's figures are
      the ``plateau_*`` ones);
    - ``<mode>_blend_ms``: one stereo frame in blend mode (warp both eyes, shared span and
      table, compose both eyes into the side-by-side buffer, with frame time stamps so the
      table is smoothed as in the console), median over ``repeat``; ``linear`` is today's
      mapping, the baseline.

    Also ``pipe_share`` (the share of fused pixels on the hot pipe, smallest over the
    frames: it is in view) and ``span_low_c``, ``span_high_c`` (the automatic span of the
    first frame, Celsius).
    """
    import numpy as np

    from trifuse.app.sources.sim.inspection import InspectionScenario
    from trifuse.fusion.agc import (
        AGC_MODES,
        DEFAULT_MAX_GAIN,
        PaletteIndexer,
        index_entropy_bits,
        tone_map,
    )
    from trifuse.fusion.compose import DisplaySettings
    from trifuse.fusion.span import resolve_span
    from trifuse.fusion.stereo import StereoFusion

    scenario = InspectionScenario(seed=0)
    rig = scenario.rig
    eyes = ("left", "right")
    people, walls, pipe = _groups([s.name for s in scenario.scene.solids])
    fusion = StereoFusion(rig)
    w, h = fusion.size
    indexer = PaletteIndexer(w, h)
    index = np.empty((h, w), np.uint8)

    variants = [(m, m, DEFAULT_MAX_GAIN) for m in AGC_MODES] + [
        (f"plateau_g{g:g}", "plateau", g) for g in MAX_GAIN_SWEEP
    ]
    entropy: dict[str, list[float]] = {v: [] for v, _, _ in variants}
    offset: dict[str, list[float]] = {v: [] for v, _, _ in variants}
    separation: dict[tuple[str, str], list[float]] = {}
    figures: dict[str, float] = {}
    pipe_share: list[float] = []
    scene_inputs = None
    for k, t_s in enumerate(AGC_TIMES_S):
        frames, truth = scenario.render(t_s)
        colors = {e: frames[rig.eyes[e].color].image for e in eyes}
        thermals = {e: frames[rig.eyes[e].thermal].image for e in eyes}
        tof = frames[fusion.tof]
        fusion.update_depth(tof.distance_m, tof.image)
        fusion.compose(colors, thermals, DisplaySettings(agc="linear"))
        kelvin = [fusion.thermal_on_color[e] for e in eyes]
        solids = [truth[rig.eyes[e].color].solid for e in eyes]
        fused = [np.isfinite(t) for t in kelvin]
        span = resolve_span(DisplaySettings(), kelvin)
        if k == 0:
            figures["span_low_c"], figures["span_high_c"] = span[0] - 273.15, span[1] - 273.15
            scene_inputs = (colors, thermals, tof)
        n_fused = sum(int(f.sum()) for f in fused)
        on_pipe = sum(int((f & np.isin(s, pipe)).sum()) for f, s in zip(fused, solids, strict=True))
        pipe_share.append(on_pipe / max(n_fused, 1))
        for variant, mode, max_gain in variants:
            tone = tone_map(kelvin, mode, span, max_gain=max_gain)
            idx = []
            for t, f in zip(kelvin, fused, strict=True):
                indexer.index(t, tone, out=index)
                idx.append(index[f])
            entropy[variant].append(index_entropy_bits(np.concatenate(idx)))
            eye_walls = [
                i[np.isin(s[f], walls)] for i, s, f in zip(idx, solids, fused, strict=True)
            ]
            wall = np.concatenate(eye_walls)
            if min(w.size for w in eye_walls) >= MIN_PIXELS:
                left, right = (float(np.median(w)) for w in eye_walls)
                offset[variant].append(left - right)
            for person, ids in people.items():
                body = np.concatenate(
                    [i[np.isin(s[f], ids)] for i, s, f in zip(idx, solids, fused, strict=True)]
                )
                if body.size < MIN_PIXELS or wall.size < MIN_PIXELS:
                    continue
                sep = (float(np.median(body)) - float(np.median(wall))) / 255.0
                separation.setdefault((variant, person), []).append(sep)

    for variant, _, _ in variants:
        figures[f"{variant}_entropy_bits"] = float(np.mean(entropy[variant]))
        seps = [min(v) for (m, _), v in separation.items() if m == variant]
        figures[f"{variant}_separation"] = min(seps) if seps else float("nan")
        steps = offset[variant]
        figures[f"{variant}_offset_steps"] = max(steps, key=abs) if steps else float("nan")
        if variant in AGC_MODES:
            for (m, person), v in sorted(separation.items()):
                if m == variant:
                    figures[f"{variant}_separation_{person}"] = min(v)
    figures["pipe_share"] = min(pipe_share)

    # Cost per stereo frame, the depth of the first frame, frame stamps 33 ms apart.
    colors, thermals, tof = scene_inputs
    fusion.update_depth(tof.distance_m, tof.image)
    for mode in AGC_MODES:
        settings = DisplaySettings(mode="blend", agc=mode)
        fusion.tone_mapper.reset()
        figures[f"{mode}_blend_ms"] = median_ms(
            lambda i, s=settings: fusion.compose(colors, thermals, s, (i + 2) * 33_000_000),
            repeat,
        )
    return figures
