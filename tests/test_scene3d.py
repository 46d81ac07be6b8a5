"""The console's 3D scene (app/server/scene3d.py) on a real Viser server with a small fake
pipeline: a real StereoFusion of the simulated head's rig fed one synthetic frame set."""

from __future__ import annotations

import contextlib
import dataclasses
import io
from collections.abc import Iterator
from types import SimpleNamespace

import numpy as np
import pytest
import viser

from app.server.board_watch import BoardSighting
from app.server.context import ConsoleContext
from app.server.scene3d import (
    DEPTH_PALETTE,
    NAN_GREY,
    TEXTURE_MAX_W,
    Scene3D,
    board_checker_image,
    rig_difference_markdown,
    sensor_texture,
    wxyz_of,
)
from app.sources.frames import Frame, FrameSet
from app.sources.sim.head import default_rig
from calib.board import Board
from calib.radiometry import Radiometry
from calib.rig import Rig
from calib.transforms import make_T, rotation_from_euler_deg
from fusion.compose import DisplaySettings
from fusion.palettes import palette_colors
from fusion.stereo import StereoFusion

RED = (200, 30, 30)
GREEN = (30, 200, 30)
LEFT_K, RIGHT_K = 305.0, 299.0
SPAN_K = (295.0, 315.0)


def synthetic_set(rig: Rig, distance_m: np.ndarray) -> FrameSet:
    """Uniform red left and green right colour images, uniform 305 K / 299 K thermal
    images, the given TOF distance (H, W) metres with a ramp amplitude."""

    def size(name: str) -> tuple[int, int]:
        w, h = rig[name].image_size
        return h, w

    frames = {
        "ccd_left": Frame("ccd_left", 1, np.full((*size("ccd_left"), 3), RED, np.uint8)),
        "ccd_right": Frame("ccd_right", 1, np.full((*size("ccd_right"), 3), GREEN, np.uint8)),
        "thermal_left": Frame("thermal_left", 1, np.full(size("thermal_left"), LEFT_K, np.float32)),
        "thermal_right": Frame(
            "thermal_right", 1, np.full(size("thermal_right"), RIGHT_K, np.float32)
        ),
        "tof": Frame(
            "tof",
            1,
            np.tile(np.linspace(100, 3000, size("tof")[1], dtype=np.float32), (size("tof")[0], 1)),
            distance_m,
        ),
    }
    return FrameSet(1, frames)


def ramp_distance(rig: Rig) -> np.ndarray:
    """TOF radial distance (H, W) float32 metres: 1.5 m at the top row to 3.5 m at the
    bottom, a NaN hole in the middle."""
    w, h = rig["tof"].image_size
    d = np.repeat(np.linspace(1.5, 3.5, h, dtype=np.float32)[:, None], w, axis=1)
    d[60:70, 80:90] = np.nan
    return d


@pytest.fixture(scope="module")
def fusion_rig() -> tuple[StereoFusion, Rig]:
    rig = default_rig()
    fusion = StereoFusion(rig)
    fusion.update_depth(ramp_distance(rig))
    return fusion, rig


@pytest.fixture
def scene(fusion_rig) -> Iterator[tuple[Scene3D, SimpleNamespace, dict[str, Rig]]]:
    fusion, rig = fusion_rig
    fusion.span_k = None
    pipeline = SimpleNamespace(
        rig=rig,
        fusion=fusion,
        tof="tof",
        latest_set=synthetic_set(rig, ramp_distance(rig)),
        settings=DisplaySettings(span_k=SPAN_K, palette="iron"),
        radiometry={"thermal_left": Radiometry(), "thermal_right": Radiometry()},
    )
    extra: dict[str, Rig] = {}
    with contextlib.redirect_stdout(io.StringIO()):
        server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    ctx = ConsoleContext(
        server=server,
        source=None,  # type: ignore[arg-type]
        description="test",
        hub=None,  # type: ignore[arg-type]
        pipeline=pipeline,  # type: ignore[arg-type]
        board=Board(9, 6, 0.04),
        board_watch=SimpleNamespace(latest=None),  # type: ignore[arg-type]
        ground_truth_rig=default_rig(),
        rig_choices=lambda: dict(extra),
    )
    s = Scene3D(ctx)
    try:
        yield s, pipeline, extra
    finally:
        server.stop()


def moved_rig(rig: Rig, sensor: str, dt_m: np.ndarray, rot_deg: float) -> Rig:
    """A copy of ``rig`` with ``sensor`` shifted by ``dt_m`` (rig frame) and turned by
    ``rot_deg`` about its own y axis."""
    s = rig[sensor]
    T = s.T_rig_sensor @ make_T(rotation_from_euler_deg(0, rot_deg, 0), np.zeros(3))
    T[:3, 3] += dt_m
    sensors = dict(rig.sensors)
    sensors[sensor] = dataclasses.replace(s, T_rig_sensor=T)
    return Rig(sensors=sensors, reference=rig.reference, eyes=dict(rig.eyes))


def same_rotation(wxyz_a: np.ndarray, wxyz_b: np.ndarray) -> bool:
    return abs(abs(float(np.dot(wxyz_a, wxyz_b))) - 1.0) < 1e-9


# -- colouring ---------------------------------------------------------------------------


def test_cloud_colour_modes_on_a_synthetic_frame_set(scene) -> None:
    s, pipeline, _ = scene
    fusion = pipeline.fusion
    s.update_cloud()
    assert s.cloud.visible
    pts = np.asarray(s.cloud.points, dtype=np.float64)
    np.testing.assert_allclose(pts, fusion.points, atol=1e-6)  # TOF frame = rig frame, m
    assert np.isfinite(pts).all() and len(pts) > 20000  # the NaN hole is left out

    # colour: the left colour camera's red where it sees the point, grey elsewhere
    colors = np.asarray(s.cloud.colors)
    red = (colors == RED).all(axis=1)
    grey = (colors == NAN_GREY).all(axis=1)
    assert (red | grey).mean() > 0.98  # bilinear blends only along the image border
    assert 0.3 < red.mean() < 0.95  # the TOF sees wider (vertically) than the colour camera

    # temperature: the left imager's 305 K in the pipeline's palette over its span
    s.cloud_mode.value = "temperature"  # runs the update, like a browser's change
    colors = np.asarray(s.cloud.colors)
    hot = tuple(palette_colors(np.array([LEFT_K]), SPAN_K, "iron")[0])
    is_hot = (colors == hot).all(axis=1)
    assert is_hot.mean() > 0.3
    assert (is_hot | (colors == NAN_GREY).all(axis=1)).mean() > 0.98
    assert s.cloud_span == SPAN_K
    assert "21.9 to 41.9 °C" in s.cloud_md.content

    # depth: radial distance in the depth palette over the 1st-99th percentile
    s.cloud_mode.value = "depth"
    colors = np.asarray(s.cloud.colors)
    r = np.linalg.norm(fusion.points.astype(np.float64), axis=1)
    lo, hi = s.cloud_span
    assert lo == pytest.approx(np.percentile(r, 1)) and hi == pytest.approx(np.percentile(r, 99))
    np.testing.assert_array_equal(colors, palette_colors(r, s.cloud_span, DEPTH_PALETTE))
    near, far = colors[np.argmin(r)], colors[np.argmax(r)]
    assert not np.array_equal(near, far)


def test_temperature_mode_uses_the_last_fused_span_and_the_offsets(scene) -> None:
    s, pipeline, _ = scene
    pipeline.settings = DisplaySettings(span_k=None, palette="rainbow")
    pipeline.fusion.span_k = (300.0, 310.0)  # what the last fused frame used
    pipeline.radiometry["thermal_left"] = Radiometry(manual_offset_k=5.0)
    s.cloud_mode.value = "temperature"
    colors = np.asarray(s.cloud.colors)
    want = tuple(palette_colors(np.array([LEFT_K + 5.0]), (300.0, 310.0), "rainbow")[0])
    assert (colors == want).all(axis=1).mean() > 0.3


def test_point_size_slider(scene) -> None:
    s, _, _ = scene
    s.point_size.value = 20.0
    assert s.cloud.point_size == pytest.approx(0.02)


# -- textures ----------------------------------------------------------------------------


def test_frustums_show_small_live_textures(scene) -> None:
    s, pipeline, _ = scene
    s.update_textures()
    for name in ("ccd_left", "ccd_right", "thermal_left", "thermal_right", "tof"):
        img = s.nodes[name].frustum.image
        assert img is not None and img.dtype == np.uint8 and img.ndim == 3, name
        assert img.shape[1] <= TEXTURE_MAX_W and img.shape[2] == 3
    assert s.nodes["ccd_left"].frustum.image.shape == (240, 320, 3)
    np.testing.assert_array_equal(s.nodes["ccd_left"].frustum.image[5, 5], RED)
    # thermal in the pipeline's palette over its span
    want = palette_colors(np.array([LEFT_K]), SPAN_K, "iron")[0]
    np.testing.assert_array_equal(s.nodes["thermal_left"].frustum.image[10, 10], want)
    # TOF amplitude stretched grey: dark at the left, bright at the right
    tof = s.nodes["tof"].frustum.image
    assert tof.shape == (144, 176, 3) and tof[70, 1, 0] < 20 and tof[70, -2, 0] > 235

    # a sensor missing from the newest set shows no image; the others keep theirs
    fs = pipeline.latest_set
    pipeline.latest_set = FrameSet(2, {k: v for k, v in fs.frames.items() if k != "thermal_right"})
    s.update_textures()
    assert s.nodes["thermal_right"].frustum.image is None
    assert s.nodes["thermal_left"].frustum.image is not None

    s.textures_on.value = False
    assert all(n.frustum.image is None for n in s.nodes.values())


def test_sensor_texture_shapes() -> None:
    thermal = np.linspace(290, 320, 382 * 288, dtype=np.float32).reshape(288, 382)
    tex = sensor_texture(thermal, "thermal")  # no span: to_display's inferno stretch
    assert tex.shape == (241, 320, 3) and tex.dtype == np.uint8
    assert not np.array_equal(tex[..., 0], tex[..., 2])  # colour-mapped, not grey
    with pytest.raises(ValueError, match=r"expected \(H, W\)"):
        sensor_texture(np.zeros((4, 4, 3), np.float32), "thermal")


def test_board_checker_image_matches_the_board() -> None:
    board = Board(9, 6, 0.04)
    img = board_checker_image(board, 4)
    assert img.shape == (7 * 4, 10 * 4, 3)
    # the square up-left of corner (0, 0) is black, its right neighbour white
    assert img[0, 0, 0] < 50 and img[0, 4, 0] > 200 and img[4, 4, 0] < 50


# -- board -------------------------------------------------------------------------------


def test_board_is_drawn_at_its_estimated_pose_and_hidden_when_lost(scene) -> None:
    s, pipeline, _ = scene
    assert not s.board_node.visible
    T = make_T(rotation_from_euler_deg(10, -20, 5), [0.1, -0.05, 1.2])
    s.ctx.board_watch.latest = BoardSighting(pipeline.latest_set, {}, T, "ccd_left", False)
    s.update_board()
    assert s.board_node.visible
    np.testing.assert_allclose(s.board_node.position, T[:3, 3], atol=1e-12)
    assert same_rotation(s.board_node.wxyz, wxyz_of(T))
    assert "1.21 m" in s.board_md.content and "ccd_left" in s.board_md.content
    assert s.live.position == pytest.approx((0, 0, 0))  # the in-use rig: identity
    s.ctx.board_watch.latest = BoardSighting(pipeline.latest_set, {}, None, None, False)
    s.update_board()
    assert not s.board_node.visible and "not detected" in s.board_md.content


# -- rigs --------------------------------------------------------------------------------


def test_switching_rig_moves_frustums_and_reports_the_difference(scene) -> None:
    s, pipeline, extra = scene
    rig = pipeline.rig
    dt = np.array([0.006, 0.0, -0.008])  # 10 mm
    other = moved_rig(rig, "ccd_left", dt, 2.0)
    extra["rig-0003 (2026-11-22 14:03)"] = other
    s.refresh_rigs()
    assert s.rig_choice.options == ("in use", "ground truth", "rig-0003 (2026-11-22 14:03)")

    frame = s.nodes["ccd_left"].frame
    np.testing.assert_allclose(frame.position, rig["ccd_left"].T_rig_sensor[:3, 3])
    s.rig_choice.value = "rig-0003 (2026-11-22 14:03)"  # as a browser's choice does
    T = other["ccd_left"].T_rig_sensor
    np.testing.assert_allclose(frame.position, T[:3, 3], atol=1e-12)
    assert same_rotation(frame.wxyz, wxyz_of(T))
    md = s.rig_md.content
    row = next(line for line in md.splitlines() if line.startswith("| ccd_left"))
    assert "| 2.000 | 10.0 |" in row, row
    row = next(line for line in md.splitlines() if line.startswith("| tof"))
    assert "| 0.000 | 0.0 |" in row, row

    # the saved version disappears: back to the rig in use
    extra.clear()
    s.refresh_rigs()
    assert s.rig_choice.value == "in use" and "rig-0003" not in " ".join(s.rig_choice.options)
    np.testing.assert_allclose(frame.position, rig["ccd_left"].T_rig_sensor[:3, 3])
    assert s.rig_md.content == "Showing the rig in use."


def test_a_rig_with_other_sensors_hides_the_missing_ones(scene) -> None:
    s, pipeline, extra = scene
    rig = pipeline.rig
    sensors = {k: v for k, v in rig.sensors.items() if k != "thermal_right"}
    # the TOF moved: the live cloud and board follow the displayed rig's TOF
    sensors["tof"] = dataclasses.replace(
        rig["tof"], T_rig_sensor=make_T(np.eye(3), [0.0, 0.0, 0.05])
    )
    extra["one eye"] = Rig(sensors=sensors, reference="tof", eyes={"left": rig.eyes["left"]})
    s.refresh_rigs()
    s.rig_choice.value = "one eye"
    assert not s.nodes["thermal_right"].frame.visible
    assert s.nodes["thermal_left"].frame.visible
    assert s.live.position == pytest.approx((0.0, 0.0, 0.05))
    assert "thermal_right | not in this rig" in s.rig_md.content


def test_rig_difference_markdown_lists_every_sensor() -> None:
    rig = default_rig()
    md = rig_difference_markdown("ground truth", rig, rig)
    assert all(f"| {n} | 0.000 | 0.0 | +0.0 |" in md for n in rig.names)


# -- robustness --------------------------------------------------------------------------


def test_tick_survives_missing_sensors_nan_depth_and_broken_parts(scene) -> None:
    s, pipeline, extra = scene
    rig = pipeline.rig
    # a frame set with the TOF and the left colour camera missing, all-NaN depth fused
    fs = pipeline.latest_set
    pipeline.latest_set = FrameSet(
        3, {k: v for k, v in fs.frames.items() if k not in ("tof", "ccd_left")}
    )
    nan_fusion = StereoFusion(rig)
    nan_fusion.update_depth(np.full((144, 176), np.nan, np.float32))
    pipeline.fusion = nan_fusion
    for mode in ("color", "temperature", "depth"):
        s.cloud_mode.value = mode
        s.tick()
        assert not s.cloud.visible, mode
    assert s.nodes["ccd_left"].frustum.image is None
    assert not s.errors, s.errors

    # no depth yet at all
    pipeline.fusion = StereoFusion(rig)
    s.tick()
    assert not s.cloud.visible and "waiting" in s.cloud_md.content

    # parts that raise: shown in the folder, the tick goes on with the others
    def broken() -> dict[str, Rig]:
        raise OSError("rig store unreadable")

    s.ctx.rig_choices = broken
    s._next_choices = s._next_texture = 0.0  # due now
    pipeline.latest_set = "not a frame set"
    s.ctx.board_watch.latest = BoardSighting(
        fs, {}, make_T(np.eye(3), [0.0, 0.0, 1.0]), "tof", False
    )
    s.tick()
    assert "rig store unreadable" in s.error_md.content
    assert "textures" in s.errors
    assert s.board_node.visible  # the board part still ran
    del extra
