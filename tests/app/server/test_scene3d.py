"""The console's 3D scene (app/server/panels/scene3d.py) on a real Viser server with a small fake
pipeline: a real StereoFusion of the simulated head's rig fed one synthetic frame set."""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Iterator
from types import SimpleNamespace

import numpy as np
import pytest
import viser.transforms as vtf

from tests.scene_support import (
    LEFT_K,
    RED,
    SPAN_K,
    pipeline_for,
    ramp_distance,
    scene_context,
)
from tests.support import FakeClock
from trifuse.app.server.panels import scene_layout as layout
from trifuse.app.server.panels.display import NEXT_RGB, scale_corners
from trifuse.app.server.panels.scene3d import Scene3D, rig_difference_markdown
from trifuse.app.server.panels.scene_board import board_checker_image, board_lag_s
from trifuse.app.server.panels.scene_cloud import DEPTH_PALETTE, NAN_GREY
from trifuse.app.server.panels.scene_sensors import (
    TEXTURE_MAX_W,
    frustum_scale,
    sensor_texture,
    vertical_fov_rad,
    wxyz_of,
)
from trifuse.app.server.panels.scene_views import FALLBACK_VIEWPORT, viewport_of
from trifuse.app.server.runtime.board_sighting import BoardSighting
from trifuse.app.sources.frames import Frame, FrameSet
from trifuse.app.sources.sim.head import default_rig
from trifuse.calib.board import Board
from trifuse.calib.radiometry import Radiometry
from trifuse.calib.rig import Rig
from trifuse.calib.transforms import make_T, rotation_from_euler_deg
from trifuse.fusion.compose import DisplaySettings
from trifuse.fusion.palettes import palette_colors
from trifuse.fusion.stereo import StereoFusion


@pytest.fixture(scope="module")
def fusion_rig() -> tuple[StereoFusion, Rig]:
    rig = default_rig()
    fusion = StereoFusion(rig)
    fusion.update_depth(ramp_distance(rig))
    return fusion, rig


@pytest.fixture
def scene(fusion_rig) -> Iterator[tuple[Scene3D, SimpleNamespace, dict[str, Rig]]]:
    fusion, _ = fusion_rig
    pipeline = pipeline_for(fusion)
    extra: dict[str, Rig] = {}
    ctx = scene_context(pipeline, ground_truth_rig=default_rig(), rig_choices=lambda: dict(extra))
    server = ctx.server
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


def test_the_image_panel_shows_small_live_images(scene) -> None:
    s, pipeline, _ = scene
    s.update_textures()
    for name in ("ccd_left", "ccd_right", "thermal_left", "thermal_right", "tof"):
        picture = s.nodes[name].picture
        assert picture.visible, name
        img = picture.image
        assert img.dtype == np.uint8 and img.ndim == 3, name
        assert img.shape[1] <= TEXTURE_MAX_W and img.shape[2] == 3
        assert not s.nodes[name].frustum.image  # the frustums are bare wireframes
    assert s.nodes["ccd_left"].picture.image.shape == (240, 320, 3)
    np.testing.assert_array_equal(s.nodes["ccd_left"].picture.image[5, 5], RED)
    # thermal in the pipeline's palette over its span
    want = palette_colors(np.array([LEFT_K]), SPAN_K, "iron")[0]
    np.testing.assert_array_equal(s.nodes["thermal_left"].picture.image[10, 10], want)
    # TOF amplitude stretched grey: dark at the left, bright at the right
    tof = s.nodes["tof"].picture.image
    assert tof.shape == (144, 176, 3) and tof[70, 1, 0] < 20 and tof[70, -2, 0] > 235

    # a sensor missing from the newest set shows no image; the others keep theirs
    fs = pipeline.latest_set
    pipeline.latest_set = FrameSet(2, {k: v for k, v in fs.frames.items() if k != "thermal_right"})
    s.update_textures()
    assert not s.nodes["thermal_right"].picture.visible
    assert s.nodes["thermal_right"].cell_node.visible  # its frame and name stay
    assert s.nodes["thermal_left"].picture.visible

    s.textures_on.value = False
    assert not any(n.picture.visible for n in s.nodes.values())


def test_thermal_images_in_raw_counts_are_shown_through_their_radiometry(scene) -> None:
    """An imager that delivers raw counts (a radiometric calibration of 0.04 K per count)
    shows the temperatures the fused picture shows: the pipeline's span is in kelvin, the
    counts (about 7,400) would all lie above it and paint the tile one colour."""
    s, pipeline, _ = scene
    fs = pipeline.latest_set
    gain = 0.04
    raw = {
        n: dataclasses.replace(f, image=(np.asarray(f.image, np.float32) / gain))
        for n, f in fs.frames.items()
        if n.startswith("thermal")
    }
    pipeline.latest_set = FrameSet(fs.stamp_ns, {**fs.frames, **raw})
    pipeline.radiometry = {n: Radiometry(gain=gain) for n in raw}
    s.update_textures()
    want = palette_colors(np.array([LEFT_K]), SPAN_K, "iron")[0]
    np.testing.assert_array_equal(s.nodes["thermal_left"].picture.image[10, 10], want)
    # the radiometry changes (a new calibration, the balance): the tile follows
    pipeline.radiometry = {n: Radiometry(gain=gain, balance_offset_k=50.0) for n in raw}
    s.update_textures()
    hot = palette_colors(np.array([SPAN_K[1]]), SPAN_K, "iron")[0]  # above the span
    np.testing.assert_array_equal(s.nodes["thermal_left"].picture.image[10, 10], hot)


def test_the_next_views_outline_is_drawn_in_the_live_images(scene) -> None:
    """``ctx.next_outline`` (full-image pixels) is drawn cyan at the texture's scale in
    that sensor's live image only, on the same frame when it changes, never into the
    frame itself; none clears it."""
    s, pipeline, _ = scene
    s.update_textures()
    plain = {n: s.nodes[n].picture.image.copy() for n in ("ccd_left", "tof")}
    frames = {n: pipeline.latest_set.frames[n].image.copy() for n in ("ccd_left", "tof")}
    w, h = s.shown_rig["ccd_left"].image_size
    box = np.array([[0.1, 0.1], [0.9, 0.1], [0.9, 0.9], [0.1, 0.9]])  # fractions of the image
    outline = box * (w, h)
    s.ctx.next_outline = {"ccd_left": outline}
    s.update_textures()
    img = s.nodes["ccd_left"].picture.image
    for x, y in scale_corners(outline, (w, h), img):
        patch = img[round(y) - 1 : round(y) + 2, round(x) - 1 : round(x) + 2].reshape(-1, 3)
        assert np.min(np.abs(patch.astype(int) - NEXT_RGB).sum(axis=1)) <= 40, (x, y)
    centre = img.shape[0] // 2, img.shape[1] // 2
    np.testing.assert_array_equal(img[centre], plain["ccd_left"][centre])
    np.testing.assert_array_equal(s.nodes["tof"].picture.image, plain["tof"])
    tw, th = s.shown_rig["tof"].image_size  # a texture at the frame's own size
    s.ctx.next_outline = {"tof": box * (tw, th)}
    s.update_textures()
    assert not np.array_equal(s.nodes["tof"].picture.image, plain["tof"])
    np.testing.assert_array_equal(s.nodes["ccd_left"].picture.image, plain["ccd_left"])
    for n, image in frames.items():
        np.testing.assert_array_equal(pipeline.latest_set.frames[n].image, image)
    s.ctx.next_outline = {}
    s.update_textures()
    np.testing.assert_array_equal(s.nodes["tof"].picture.image, plain["tof"])


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
    assert not s.nodes["ccd_left"].picture.visible
    assert not s.errors, s.errors

    # no depth yet at all
    pipeline.fusion = StereoFusion(rig)
    s.tick()
    assert not s.cloud.visible and "waiting" in s.cloud_md.content

    # parts that raise: shown in the folder, the tick goes on with the others
    def broken() -> dict[str, Rig]:
        raise OSError("rig store unreadable")

    s.ctx.rig_choices = broken
    s.clock = FakeClock(time.monotonic() + 60.0)  # a minute on: every part is due
    pipeline.latest_set = "not a frame set"
    s.ctx.board_watch.latest = BoardSighting(
        fs, {}, make_T(np.eye(3), [0.0, 0.0, 1.0]), "tof", False
    )
    s.tick()
    assert "rig store unreadable" in s.error_md.content
    assert "textures" in s.errors
    assert s.board_node.visible  # the board part still ran
    del extra


# -- first sight: frustum size, image panel, labels, views -------------------------------


def room_cloud(rig: Rig, half_width_m: float = 3.5, depth_m: float = 8.3) -> np.ndarray:
    """(N, 3) what the TOF camera of ``rig`` sees in a box room (rig frame, metres): its
    pixel rays up to the walls at x = +-``half_width_m``, the ceiling at y = -1.6, the
    floor at y = 1.2 and the far wall at z = ``depth_m`` (the head at the origin)."""
    tof = rig["tof"]
    w, h = tof.image_size
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    rays = tof.intrinsics.unproject(np.stack([u.ravel(), v.ravel()], axis=1))
    rays = rays @ tof.T_rig_sensor[:3, :3].T
    with np.errstate(divide="ignore"):
        t_x = np.where(rays[:, 0] != 0, half_width_m / np.abs(rays[:, 0]), np.inf)
        t_y = np.where(rays[:, 1] < 0, -1.6 / rays[:, 1], np.inf)
        t_y = np.minimum(t_y, np.where(rays[:, 1] > 0, 1.2 / rays[:, 1], np.inf))
        t_z = depth_m / rays[:, 2]
    t = np.minimum(np.minimum(t_x, t_y), t_z)
    return rays * t[:, None] + tof.T_rig_sensor[:3, 3]


VIEWPORTS = ((800, 600), (1280, 800), (1920, 1080))


def first_sight(rig: Rig) -> tuple[layout.SceneBox, layout.Panel]:
    """The scene box of :func:`room_cloud` and the image panel Scene3D lays out for it."""
    box = layout.scene_box(room_cloud(rig), Scene3D._positions(rig))
    assert box is not None
    panel = layout.image_panel(
        {n: s.T_rig_sensor[:3, 3] for n, s in rig.sensors.items()},
        {n: s.width / s.height for n, s in rig.sensors.items()},
        layout.panel_image_width(box),
    )
    return box, panel


def test_the_default_frustum_depth_comes_from_the_scene() -> None:
    rig = default_rig()
    cloud = room_cloud(rig, 1.2, 1.8)  # a small room: no bound applies
    box = layout.scene_box(cloud, Scene3D._positions(rig))
    head = layout.head_width(Scene3D._positions(rig))
    assert 0.11 < head < 0.13  # the default head: ccd_left to ccd_right, 12 cm
    assert box.median_z == pytest.approx(np.median(cloud[:, 2]))
    assert 1.2 < box.median_z <= 1.8
    depth = layout.default_frustum_depth(box, head)
    assert depth == pytest.approx(round(0.25 * box.median_z, 2))
    # a scene close by: at least 2.5 head widths; a huge one: at most 0.5 m
    near = layout.scene_box(room_cloud(rig, 0.5, 0.6), Scene3D._positions(rig))
    assert layout.default_frustum_depth(near, head) == pytest.approx(round(2.5 * head, 2))
    far = layout.scene_box(room_cloud(rig, 30.0, 60.0), Scene3D._positions(rig))
    assert layout.default_frustum_depth(far, head) == 0.5


def test_frustum_scale_gives_viser_the_depth() -> None:
    """Viser 1.1.1 normalises a frustum to unit volume (client CameraFrustumVariants.tsx):
    its image plane lies scale / cbrt(tan(fov/2)^2 aspect / 3) in front of the apex."""
    fov, aspect = np.radians(40.0), 4.0 / 3.0
    y = np.tan(fov / 2)
    volume_scale = np.cbrt(y * (y * aspect) * 1.0 / 3.0)
    assert frustum_scale(0.9, fov, aspect) / volume_scale == pytest.approx(0.9)


def test_the_first_cloud_sizes_the_frustums_unless_the_operator_did(scene) -> None:
    s, pipeline, _ = scene
    assert s.box is None and not s.user_sized
    s.update_cloud()
    head = layout.head_width(Scene3D._positions(pipeline.rig))
    want = layout.default_frustum_depth(s.box, head)
    assert s.box.median_z == pytest.approx(np.median(pipeline.fusion.points[:, 2]), rel=0.01)
    assert s.frustum_size.value == pytest.approx(want) and not s.user_sized
    for nodes in s.nodes.values():
        f = nodes.frustum
        assert f.scale == pytest.approx(frustum_scale(want, f.fov, f.aspect))
    # the image panel hangs below the head, one picture per sensor, none overlapping
    panel = s.panel
    assert set(panel.cells) == set(pipeline.rig.names)
    corners = panel.corners()
    assert corners[:, 1].min() > max(p[1] for p in Scene3D._positions(pipeline.rig))
    assert s.nodes["ccd_left"].picture.render_width == pytest.approx(
        layout.panel_image_width(s.box)
    )


def test_the_operators_frustum_size_is_kept(scene) -> None:
    s, _, _ = scene
    s.frustum_size.value = 0.37  # as an operator's slider does, before the first cloud
    assert s.user_sized
    s.update_cloud()
    assert s.box is not None and s.frustum_size.value == pytest.approx(0.37)
    f = s.nodes["tof"].frustum
    assert f.scale == pytest.approx(frustum_scale(0.37, f.fov, f.aspect))


@pytest.mark.parametrize("viewport", VIEWPORTS)
def test_at_the_default_view_labels_and_pictures_stay_apart(viewport) -> None:
    """The overview of a room: no two sensor names overlap (their screen boxes from the
    text size), no picture covers another or any of the cloud, and all of it lies in the
    canvas left of Viser's control panel."""
    rig = default_rig()
    box, panel = first_sight(rig)
    pose = layout.view_pose("overview", box, viewport, extra=panel.corners())
    names = list(panel.cells)
    anchors = layout.project(np.stack([panel.label_points()[n] for n in names]), pose, viewport)
    boxes = layout.label_boxes(names, anchors)
    assert layout.overlapping_labels(boxes) == []
    # every label is at least the text size (one em) away from the others
    gap = min(
        max(
            boxes[j, 0] - boxes[i, 2],
            boxes[i, 0] - boxes[j, 2],
            boxes[j, 1] - boxes[i, 3],
            boxes[i, 1] - boxes[j, 3],
        )
        for i in range(len(names))
        for j in range(i + 1, len(names))
    )
    assert gap >= layout.LABEL_EM_PX, gap
    # pictures: projected quads apart from each other and from the cloud's points
    cloud_px = layout.project(box.sample, pose, viewport)
    quads = {}
    for name, cell in panel.cells.items():
        cx, cy, cz = cell.center
        w, h = cell.width / 2, cell.height / 2
        local = np.array(
            [[cx - w, cy - h, cz], [cx + w, cy - h, cz], [cx + w, cy + h, cz], [cx - w, cy + h, cz]]
        )
        q = layout.project(panel.to_rig(local), pose, viewport)
        quads[name] = (q.min(axis=0), q.max(axis=0))
        lo, hi = quads[name]
        assert hi[0] - lo[0] > 40, (name, hi - lo)  # big enough to read
        inside = np.all((cloud_px >= lo) & (cloud_px <= hi), axis=1)
        assert not inside.any(), f"{name}'s picture covers {inside.sum()} cloud points"
    for i, a in enumerate(names):
        for b in names[i + 1 :]:
            (alo, ahi), (blo, bhi) = quads[a], quads[b]
            assert (ahi < blo).any() or (bhi < alo).any(), (a, b)
    free_w, _ = layout.free_canvas(viewport)
    everything = np.vstack([cloud_px, layout.project(panel.corners(), pose, viewport)])
    assert everything[:, 0].min() >= 0 and everything[:, 0].max() <= free_w
    assert everything[:, 1].min() >= 0 and everything[:, 1].max() <= viewport[1]


def test_crowded_labels_are_caught() -> None:
    """The check itself: two names at the same spot overlap, a line apart they do not."""
    boxes = layout.label_boxes(["ccd_left", "thermal_left"], np.array([[100.0, 50], [104, 55]]))
    assert layout.overlapping_labels(boxes) == [(0, 1)]
    boxes = layout.label_boxes(["ccd_left", "thermal_left"], np.array([[100.0, 50], [104, 70]]))
    assert layout.overlapping_labels(boxes) == []


class FakeCamera:
    """What Scene3D sets on a browser's camera, recorded (Viser's CameraHandle API)."""

    def __init__(self, width: int | None = 800, height: int | None = 600) -> None:
        if width is not None:
            self.image_width, self.image_height = width, height
        self.fov = self.near = None
        self.up_direction = self.position = self.look_at = None


def press(button, client) -> None:
    """Run a Viser button's click callbacks as a browser's click does."""
    for cb in button._impl.update_cb:
        cb(SimpleNamespace(client=client, client_id=1, target=button))


def test_view_buttons_move_the_camera_of_the_client_that_pressed(scene) -> None:
    s, pipeline, _ = scene
    s.update_cloud()
    points = pipeline.fusion.points
    client, other = SimpleNamespace(camera=FakeCamera()), SimpleNamespace(camera=FakeCamera())
    vfov = max(vertical_fov_rad(x) for x in pipeline.rig.sensors.values())

    press(s.view_buttons["View from head"], client)
    cam = client.camera
    assert cam.position == (0.0, 0.0, 0.0) and cam.up_direction == (0.0, -1.0, 0.0)
    assert cam.look_at[:2] == (0.0, 0.0) and cam.look_at[2] > 1.0  # along +z
    assert cam.fov == pytest.approx(1.15 * vfov)
    # the frustums' ends are clipped away, the scene (1.5 m on) is not
    assert cam.near == pytest.approx(1.05 * s.frustum_size.value)
    assert cam.near < np.percentile(points[:, 2], 2)
    s.frustum_size.value = 1.2  # deeper frustums: never clipped beyond 0.55 m
    press(s.view_buttons["View from head"], client)
    assert cam.near == pytest.approx(0.55)
    assert other.camera.position is None  # only the browser that pressed

    for label, check in (
        ("View from above", lambda d: d[1] > 0.9),  # looking down (+y)
        ("View from side", lambda d: d[0] < -0.99),  # from the right, looking left (-x)
        ("Overview", lambda d: d[1] > 0.4 and d[2] > 0.7),  # forward and down
    ):
        press(s.view_buttons[label], client)
        cam = client.camera
        d = np.subtract(cam.look_at, cam.position)
        assert check(d / np.linalg.norm(d)), (label, d)
        assert cam.near == pytest.approx(0.01) and cam.up_direction == (0.0, -1.0, 0.0)
        # the framed cloud lies in the canvas left of the control panel
        pose = layout.CameraPose(cam.position, cam.look_at, cam.up_direction, cam.fov)
        px = layout.project(s.box.sample, pose, (800, 600))
        assert np.isfinite(px).all() and px[:, 0].min() > 0 and px[:, 0].max() < 800 - 345
        assert px[:, 1].min() > 0 and px[:, 1].max() < 600

    # a browser that has not told its canvas size: framed for a common one
    blind = SimpleNamespace(camera=FakeCamera(None, None))
    press(s.view_buttons["View from above"], blind)
    assert blind.camera.position is not None
    assert viewport_of(blind.camera) == FALLBACK_VIEWPORT


class FakeClientScene:
    """A browser's own scene (``client.scene``): the frames added, and removed."""

    def __init__(self) -> None:
        self.frames: list[SimpleNamespace] = []

    def add_frame(self, name: str, **props) -> SimpleNamespace:
        handle = SimpleNamespace(name=name, removed=False, **props)
        handle.remove = lambda: setattr(handle, "removed", True)
        self.frames.append(handle)
        return handle


def test_the_image_panel_faces_the_view_of_the_browser_that_chose_it(scene) -> None:
    """Another view turns the panel for that browser only (a client-scoped /panel that
    shadows the shared one); the overview gives it back the shared panel."""
    s, _, _ = scene
    s.update_cloud()
    client = SimpleNamespace(client_id=3, camera=FakeCamera(), scene=FakeClientScene())
    shared = s.panel_node.wxyz.copy()
    press(s.view_buttons["View from side"], client)
    (side,) = client.scene.frames
    assert side.name == "/panel" and side.visible
    R = vtf.SO3(np.asarray(side.wxyz)).as_matrix()
    np.testing.assert_allclose(R[:, 2], [-1.0, 0.0, 0.0], atol=1e-9)  # faces +x
    np.testing.assert_allclose(R[:, 1], [0.0, 1.0, 0.0], atol=1e-9)  # upright (down +y)
    assert side.position[1] > 0.1  # below the head
    np.testing.assert_array_equal(s.panel_node.wxyz, shared)  # the others' panel stays
    # the side view's labels, now facing the camera, stay apart
    placed = s.panel.placed("side")
    names = list(placed.cells)
    cam = client.camera
    pose = layout.CameraPose(cam.position, cam.look_at, cam.up_direction, cam.fov)
    anchors = layout.project(np.stack([placed.label_points()[n] for n in names]), pose, (800, 600))
    assert layout.overlapping_labels(layout.label_boxes(names, anchors)) == []
    press(s.view_buttons["View from head"], client)  # out of the way from the head
    assert side.removed and not client.scene.frames[-1].visible
    press(s.view_buttons["Overview"], client)
    assert client.scene.frames[-1].removed and len(client.scene.frames) == 2


def test_the_canvas_is_the_largest_drawing_size_a_browser_reported(scene) -> None:
    """Viser reports its drawing buffer, which it shrinks to 0.75 x while drawing is slow:
    views are framed for the canvas (the largest size at the present aspect ratio)."""
    s, _, _ = scene
    client = SimpleNamespace(client_id=7, camera=FakeCamera(800, 600))
    s._note_canvas(7, client.camera)
    client.camera.image_width, client.camera.image_height = 600, 450  # drawing slowly
    s._note_canvas(7, client.camera)
    assert s.canvas_of(client) == (800, 600)
    press(s.view_buttons["Overview"], client)
    want = s.view_pose("overview", (800, 600))
    assert client.camera.position == pytest.approx(want.position)
    client.camera.image_width, client.camera.image_height = 1000, 500  # window resized
    s._note_canvas(7, client.camera)
    assert s.canvas_of(client) == (1000, 500)


def test_a_view_needs_no_cloud_and_an_unknown_view_is_refused(scene) -> None:
    s, _, _ = scene
    client = SimpleNamespace(camera=FakeCamera())
    s.set_view(client, "overview")  # before any cloud: the default room
    assert client.camera.position is not None
    with pytest.raises(ValueError, match="expected one of overview, head, above, side"):
        s.view_pose("below", (800, 600))


def test_the_board_moves_when_the_watch_publishes_and_says_how_late(scene) -> None:
    s, pipeline, _ = scene
    listeners = []
    s.ctx.board_watch = SimpleNamespace(latest=None, latest_pose=None, pose_listeners=listeners)
    s2 = Scene3D(s.ctx)  # registers with the watch
    assert len(listeners) == 1
    fs = pipeline.latest_set
    T = make_T(rotation_from_euler_deg(0, 10, 0), [0.2, 0.1, 1.5])
    sighting = BoardSighting(fs, {}, T, "ccd_left", False, False)
    s.ctx.board_watch.latest_pose = sighting
    listeners[0](sighting)  # what the watch does when it publishes: no tick needed
    assert s2.board_node.visible
    np.testing.assert_allclose(s2.board_node.position, T[:3, 3])
    assert "searching the other sensors" in s2.board_md.content
    assert "older" not in s2.board_md.content
    # 2 s later, the same picture (the very images): the board is not late
    pipeline.latest_set = FrameSet(fs.stamp_ns + 2_000_000_000, dict(fs.frames))
    assert board_lag_s(sighting, pipeline.latest_set) == 0.0
    # a new picture 2 s later: the board drawn is 2 s late
    moved = {k: Frame(k, 3, np.array(v.image), v.distance_m) for k, v in fs.frames.items()}
    pipeline.latest_set = FrameSet(fs.stamp_ns + 2_000_000_000, moved)
    assert board_lag_s(sighting, pipeline.latest_set) == pytest.approx(2.0)
    complete = BoardSighting(fs, {}, T, "ccd_left", False)
    s.ctx.board_watch.latest_pose = complete
    listeners[0](complete)
    assert "(in frames 2.0 s older than the cloud)" in s2.board_md.content
