"""Where the 3D console puts things and where it looks from: pure geometry for
:mod:`app.server.panels.scene3d` (arrays in, values out; no Viser).

Everything is in the rig frame (OpenCV axes: +x right, +y down, +z forward; metres); the
scene's "up" is -y.

The problem this module solves: the sensor head is about 15 cm wide, the scene it looks at
0.5-8 m away. Frustums at the head's scale are a dot in a view of the scene, and frustums
at the scene's scale, all starting within a few centimetres of each other and looking the
same way, lie on top of each other: their live images cover each other whatever their
size (the left colour camera and the left thermal imager are 3 cm apart, so their images
overlap as soon as the frustums are deeper than 4 cm), and their labels collide. Hence:

- **The frustums stay at their true poses** (they show the rig's geometry, and the "Rig
  shown" comparison depends on it) and are drawn as wireframes at a depth taken from the
  scene (:func:`default_frustum_depth`: a quarter of the cloud's median distance, at
  least 2.5 head widths, at most 0.5 m), so that they reach visibly into the scene from
  the default view; the view from the head clips them away (near plane just beyond
  their ends, never beyond 0.55 m).
- **The live images are spread out** (:func:`image_panel`): a panel of pictures hanging
  just below the head, laid out as the sensors sit on the head (columns of sensors at
  about the same x, left to right, rows top to bottom), each framed in its frustum's
  colour, facing the default view (and, for a browser that chose another view, that
  view: :meth:`Panel.placed`); each picture is a fifth of the scene's width wide
  (:func:`panel_image_width`), so that it can be read from a view of the whole scene.
  Seen from behind and above the head (the default view, :func:`view_pose`), everything
  the TOF camera sees projects above the head on the screen, so the panel below it
  covers none of the cloud, and no picture covers another.
- **Labels sit under their pictures** (:func:`label_anchor`), a picture's width apart,
  so the names do not overlap at the default view; :func:`overlapping_labels` checks that
  for a given view and canvas (the tests use it).
- **Views** (:func:`view_pose`): the default overview, from the head (at the rig origin
  looking along +z, -y up: what the sensors see), from above and from the side, each
  framing the scene (:class:`SceneBox`: a sample of the cloud's points) and the panel in
  the part of the browser's canvas that Viser's floating control panel (:data:`PANEL_PX`
  on the right) leaves free.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

PANEL_PX = 345
"""Width of Viser's floating control panel (20 em of 16 px plus its margins), CSS pixels,
on the right of the canvas: views are framed in the canvas left of it."""
PANEL_MIN_CANVAS_PX = 700
"""Below this canvas width the panel is assumed to cover the scene anyway (not framed)."""
VIEW_FOV_RAD = float(np.radians(55.0))
"""Vertical field of view of the overview, above and side views."""
VIEW_MARGIN = 0.9
"""Framed points fill at most this fraction of the free canvas."""
FRAME_ROUNDS = 3
"""Re-centring rounds of :func:`frame_points`."""
OVERVIEW_ELEVATION_RAD = float(np.radians(32.0))
"""The default view looks down at the scene from behind the head at this angle: steeper
than half the TOF camera's vertical field of view (23.5 deg), so that everything the TOF
sees projects above the head on the screen and the picture panel below it covers none."""
ABOVE_ELEVATION_RAD = float(np.radians(70.0))
"""The view from above looks down at this angle from behind the head ("up" on the screen
is +z, away from the head): steep enough for a floor plan, not so steep that the image
panel (tilted to face the overview) is seen edge-on and its names run together."""
HEAD_FOV_MARGIN = 1.15
"""The view from the head widens the widest sensor's vertical field of view by this."""
NEAR_M = 0.01
"""Near clipping distance of the views (Viser's default), metres."""
HEAD_NEAR_BEYOND = 1.05
"""The view from the head clips what lies nearer than this many frustum depths (the
frustums' own lines, which would cross the view from the other sensors' apexes), but
never more than :data:`HEAD_NEAR_MAX_M`."""
HEAD_NEAR_MAX_M = 0.55
"""The view from the head never clips beyond this distance: a board held 0.6 m from the
head stays in view (a frustum made deeper than 0.52 m shows its far end there)."""

DEPTH_PER_MEDIAN = 0.25
"""Default frustum depth as a fraction of the cloud's median distance (z)."""
MIN_DEPTH_HEADS = 2.5
"""Default frustum depth at least this many head widths."""
DEPTH_RANGE_M = (0.1, 0.5)
"""Default frustum depth within these bounds, metres: at most 0.5 m, so that the view from
the head can clip the frustums away (:data:`HEAD_NEAR_MAX_M`)."""
IMAGE_PER_WIDTH = 0.2
"""Width of each picture of the image panel as a fraction of the scene's width (x)..."""
IMAGE_WIDTH_RANGE_M = (0.3, 2.0)
"""... within these bounds, metres."""
IMAGE_GAP = 0.12
"""Gap between the panel's pictures, as a fraction of a picture's width."""
LABEL_BAND = 0.32
"""Room under each picture for its label, as a fraction of a picture's width."""
PANEL_DROP = 0.35
"""The panel's top edge hangs this far (fraction of a picture's width) below the head."""

LABEL_EM_PX = 12.0
"""Viser's screen-space labels: 12 CSS px per em at ``font_screen_scale`` 1."""
LABEL_CHAR_EM = 0.62
"""Average advance of a character of Viser's label font (generous), in em."""
LABEL_LINE_EM = 1.4
"""Height of a one-line label with its background, in em."""


@dataclass(frozen=True, eq=False)
class SceneBox:
    """What the console shows, robustly: rig frame, metres (compared by identity).

    Attributes:
        lo, hi: (3,) corners of the box from the 0.5th to the 99.5th percentile of the
            cloud per axis, widened to contain the head (the rig origin and the sensors).
        median_z: the cloud's median distance along the optical axis (z), metres.
        sample: (M, 3) up to :data:`SAMPLE_POINTS` cloud points inside the box and the
            head's points: what the views frame (a pyramid of points fills far less of
            the screen than its bounding box).
    """

    lo: tuple[float, float, float]
    hi: tuple[float, float, float]
    median_z: float
    sample: np.ndarray

    @property
    def center(self) -> np.ndarray:
        return (np.asarray(self.lo) + np.asarray(self.hi)) / 2.0

    def corners(self) -> np.ndarray:
        """(8, 3) the box's corners."""
        lo, hi = np.asarray(self.lo), np.asarray(self.hi)
        idx = np.array([[i >> 2 & 1, i >> 1 & 1, i & 1] for i in range(8)])
        return np.where(idx == 1, hi, lo)


def _box(
    lo: tuple[float, float, float], hi: tuple[float, float, float], median_z: float
) -> SceneBox:
    b = SceneBox(lo, hi, median_z, np.zeros((0, 3)))
    return SceneBox(lo, hi, median_z, b.corners())


DEFAULT_BOX = _box((-2.5, -1.5, 0.0), (2.5, 1.5, 5.0), 3.0)
"""What the views frame before the first TOF frame: a room 5 m wide, 3 m high, 5 m deep."""

MIN_POINTS = 50
SAMPLE_POINTS = 2000


def scene_box(points: np.ndarray, head: np.ndarray | None = None) -> SceneBox | None:
    """The :class:`SceneBox` of a point cloud (and the head), or None with fewer than
    :data:`MIN_POINTS` finite points.

    Args:
        points: (N, 3) rig frame, metres (rows with NaN are ignored).
        head: (M, 3) points that must be inside too (the sensors' positions); the rig
            origin always is.
    """
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    p = p[np.isfinite(p).all(axis=1)]
    if len(p) < MIN_POINTS:
        return None
    lo, hi = np.percentile(p, [0.5, 99.5], axis=0)
    inside = p[np.all((p >= lo) & (p <= hi), axis=1)]
    step = max(1, len(inside) // SAMPLE_POINTS)
    extra = np.zeros((1, 3)) if head is None else np.vstack([np.zeros((1, 3)), head])
    lo = np.minimum(lo, extra.min(axis=0))
    hi = np.maximum(hi, extra.max(axis=0))
    median_z = float(np.median(p[:, 2]))
    sample = np.vstack([inside[::step], extra])
    return SceneBox(tuple(map(float, lo)), tuple(map(float, hi)), median_z, sample)


def head_width(positions: np.ndarray) -> float:
    """The head's size: the largest extent of the sensors' positions (N, 3) along x or y,
    metres (at least 5 cm, so that a one-sensor rig still gets a size)."""
    p = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    if len(p) == 0:
        return 0.05
    return float(max(0.05, np.ptp(p[:, 0]), np.ptp(p[:, 1])))


def default_frustum_depth(box: SceneBox, head_width_m: float) -> float:
    """The frustums' depth (metres) on first sight: :data:`DEPTH_PER_MEDIAN` of the
    cloud's median distance, at least :data:`MIN_DEPTH_HEADS` head widths, within
    :data:`DEPTH_RANGE_M`; rounded to the slider's centimetre steps."""
    depth = max(DEPTH_PER_MEDIAN * box.median_z, MIN_DEPTH_HEADS * head_width_m)
    return round(float(np.clip(depth, *DEPTH_RANGE_M)), 2)


def panel_image_width(box: SceneBox) -> float:
    """Width (metres) of each picture of the image panel: :data:`IMAGE_PER_WIDTH` of the
    scene's width, within :data:`IMAGE_WIDTH_RANGE_M` (big enough to read from a view
    of the whole scene)."""
    width = IMAGE_PER_WIDTH * (box.hi[0] - box.lo[0])
    return round(float(np.clip(width, *IMAGE_WIDTH_RANGE_M)), 2)


# -- the picture panel ---------------------------------------------------------------------


@dataclass(frozen=True)
class Cell:
    """One picture of the panel: centre (3,) in the panel's frame (x right, y down the
    panel, z into it; metres), width and height in metres. The picture lies in the
    panel's plane, its rows along +y, seen from -z like the sensor's image from behind."""

    center: tuple[float, float, float]
    width: float
    height: float

    def outline(self) -> np.ndarray:
        """(4, 2, 3) the picture's edges as line segments, relative to its centre."""
        w, h = self.width / 2.0, self.height / 2.0
        c = np.array([[-w, -h, 0.0], [w, -h, 0.0], [w, h, 0.0], [-w, h, 0.0]])
        return np.stack([c, np.roll(c, -1, axis=0)], axis=1)

    def corners(self) -> np.ndarray:
        """(4, 3) the picture's corners with the label band under it, panel frame."""
        cx, cy, cz = self.center
        w, h = self.width / 2.0, self.height / 2.0
        b = h + LABEL_BAND * self.width
        return np.array(
            [[cx - w, cy - h, cz], [cx + w, cy - h, cz], [cx + w, cy + b, cz], [cx - w, cy + b, cz]]
        )


def label_anchor(cell: Cell) -> np.ndarray:
    """(3,) where a sensor's label hangs (anchor "top-center"), panel frame: just under
    its picture."""
    cx, cy, cz = cell.center
    return np.array([cx, cy + cell.height / 2.0 + 0.04 * cell.width, cz])


@dataclass(frozen=True, eq=False)
class Panel:
    """The live images' panel (compared by identity).

    Attributes:
        T_rig_panel: (4, 4) the panel's pose: origin in the middle of its top edge, x
            right, y down the panel, z into it; it faces a view's camera (x and y along
            the screen's right and down, z along the view), hanging ``drop`` metres
            below ``anchor`` on the screen (:meth:`placed`).
        cells: sensor -> :class:`Cell` (panel frame).
        anchor: (3,) the head's centre (the sensors' mean position), rig frame, metres.
        drop: from the head's centre to the panel's top edge, metres.
    """

    T_rig_panel: np.ndarray
    cells: dict[str, Cell]
    anchor: np.ndarray
    drop: float

    def placed(self, view: str) -> Panel:
        """The same panel facing the camera of ``view`` (:data:`VIEWS`), below the head on
        the screen."""
        forward, up = view_axes(view)
        right, down, f = _basis(forward, up)
        T = np.eye(4)
        T[:3, :3] = np.stack([right, down, f], axis=1)
        T[:3, 3] = self.anchor + down * self.drop
        return Panel(T, self.cells, self.anchor, self.drop)

    def to_rig(self, points: np.ndarray) -> np.ndarray:
        """(N, 3) panel-frame points in the rig frame."""
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        return p @ self.T_rig_panel[:3, :3].T + self.T_rig_panel[:3, 3]

    def corners(self) -> np.ndarray:
        """(4 N, 3) every picture's corners with its label band, rig frame."""
        return self.to_rig(np.vstack([c.corners() for c in self.cells.values()]))

    def label_points(self) -> dict[str, np.ndarray]:
        """Sensor -> (3,) its label's anchor, rig frame."""
        return {n: self.to_rig(label_anchor(c))[0] for n, c in self.cells.items()}


def columns_of(positions: Mapping[str, np.ndarray], tolerance_m: float) -> list[list[str]]:
    """Sensors grouped into columns: sorted by x, a new column wherever the next sensor
    is more than ``tolerance_m`` right of the previous one; each column top to bottom
    (ascending y)."""
    names = sorted(positions, key=lambda n: (float(positions[n][0]), n))
    cols: list[list[str]] = []
    last_x = -np.inf
    for n in names:
        x = float(positions[n][0])
        if not cols or x - last_x > tolerance_m:
            cols.append([])
        cols[-1].append(n)
        last_x = x
    return [sorted(c, key=lambda n: (float(positions[n][1]), n)) for c in cols]


def image_panel(
    positions: Mapping[str, np.ndarray],
    aspects: Mapping[str, float],
    image_width_m: float,
    view: str = "overview",
) -> Panel:
    """The live images' panel: one :class:`Cell` per sensor, laid out as the sensors sit
    on the head (columns of sensors within a quarter head width in x, left to right; in
    each column top to bottom), hanging :data:`PANEL_DROP` picture widths below the head
    on the screen of ``view``, facing its camera (:meth:`Panel.placed`).

    Args:
        positions: sensor -> (3,) position in the rig frame, metres.
        aspects: sensor -> image width / height.
        image_width_m: every picture's width, metres.
    Raises:
        ValueError: no sensors, a non-positive width or aspect.
    """
    if not positions:
        raise ValueError("image_panel: expected at least one sensor position, got none")
    if not image_width_m > 0:
        raise ValueError(f"image_panel: expected a positive picture width, got {image_width_m}")
    bad = {n: a for n, a in aspects.items() if not a > 0}
    if bad or set(aspects) < set(positions):
        raise ValueError(
            f"image_panel: expected a positive aspect ratio for each of {sorted(positions)}, "
            f"got {dict(aspects)}"
        )
    p = {n: np.asarray(v, dtype=np.float64) for n, v in positions.items()}
    allp = np.stack(list(p.values()))
    cols = columns_of(p, tolerance_m=0.25 * head_width(allp))
    w = image_width_m
    heights = {n: w / float(aspects[n]) for n in p}
    n_rows = max(len(c) for c in cols)
    row_h = [
        max((heights[c[r]] for c in cols if r < len(c)), default=0.0) + LABEL_BAND * w
        for r in range(n_rows)
    ]
    pitch = w * (1.0 + IMAGE_GAP)
    cells: dict[str, Cell] = {}
    for i, col in enumerate(cols):
        y = 0.0
        for r, name in enumerate(col):
            x = (i - (len(cols) - 1) / 2.0) * pitch
            cells[name] = Cell((x, y + heights[name] / 2.0, 0.0), w, heights[name])
            y += row_h[r]
    anchor = allp.mean(axis=0)
    drop = float(np.max(np.linalg.norm(allp - anchor, axis=1))) + PANEL_DROP * w
    return Panel(np.eye(4), cells, anchor, drop).placed(view)


# -- views ---------------------------------------------------------------------------------


@dataclass(frozen=True)
class CameraPose:
    """A viewer camera: ``position`` and ``look_at`` (3,) in the rig frame, metres;
    ``up`` (3,) the screen's up direction; ``fov_rad`` the vertical field of view;
    ``near_m`` the near clipping distance."""

    position: tuple[float, float, float]
    look_at: tuple[float, float, float]
    up: tuple[float, float, float]
    fov_rad: float
    near_m: float = NEAR_M


VIEWS = ("overview", "head", "above", "side")


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v)


def _basis(forward: np.ndarray, up: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Camera axes (OpenCV: right, down, forward) for a view along ``forward``."""
    f = _unit(forward)
    down = -up - np.dot(-up, f) * f
    d = _unit(down)
    return np.cross(d, f), d, f


def free_canvas(viewport: tuple[int, int]) -> tuple[float, float]:
    """(free width, horizontal offset of the free area's centre from the canvas centre),
    CSS pixels, for a ``viewport`` (width, height) with Viser's panel on the right."""
    w = float(viewport[0])
    if w < PANEL_MIN_CANVAS_PX:
        return w, 0.0
    return w - PANEL_PX, -PANEL_PX / 2.0


def frame_points(
    points: np.ndarray,
    forward: np.ndarray,
    up: np.ndarray,
    fov_rad: float,
    viewport: tuple[int, int],
) -> CameraPose:
    """The camera looking along ``forward`` that shows all ``points`` (N, 3) inside the
    free part of the canvas (:func:`free_canvas`, within :data:`VIEW_MARGIN` of it), as
    large as it can.

    The distance is the smallest at which every point projects inside the free area
    (pinhole projection, bisection to 0.1 %); then camera and look-at point move sideways
    (and up or down) together so that the points' projected extent is centred in the free
    area, and the distance is found again (:data:`FRAME_ROUNDS` times: perspective makes
    the extent lopsided).
    """
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    right, down, f = _basis(np.asarray(forward, float), np.asarray(up, float))
    centre = (p.min(axis=0) + p.max(axis=0)) / 2.0
    h_px = float(viewport[1])
    free_w, shift_px = free_canvas(viewport)
    focal = (h_px / 2.0) / np.tan(fov_rad / 2.0)
    u_mid, v_mid = viewport[0] / 2.0 + shift_px, h_px / 2.0
    up_t = tuple(map(float, up))

    def pose_at(target: np.ndarray, dist: float) -> CameraPose:
        # the target appears at (u_mid, v_mid): camera and look-at moved sideways
        look = target + right * (-shift_px / focal * dist)
        return CameraPose(
            tuple(map(float, look - f * dist)), tuple(map(float, look)), up_t, float(fov_rad)
        )

    def fits(target: np.ndarray, dist: float) -> bool:
        px = project(p, pose_at(target, dist), viewport)
        if not np.isfinite(px).all():
            return False
        return bool(
            np.all(np.abs(px[:, 0] - u_mid) <= VIEW_MARGIN * free_w / 2.0)
            and np.all(np.abs(px[:, 1] - v_mid) <= VIEW_MARGIN * h_px / 2.0)
        )

    def fit(target: np.ndarray) -> float:
        lo, hi = 0.0, max(1e-3, float(np.max(np.linalg.norm(p - target, axis=1))))
        while not fits(target, hi):
            lo, hi = hi, 2.0 * hi
        while hi - lo > 1e-3 * hi:
            mid = (lo + hi) / 2.0
            lo, hi = (lo, mid) if fits(target, mid) else (mid, hi)
        return hi

    dist = fit(centre)
    for _ in range(FRAME_ROUNDS):
        px = project(p, pose_at(centre, dist), viewport)
        du = (px[:, 0].min() + px[:, 0].max()) / 2.0 - u_mid
        dv = (px[:, 1].min() + px[:, 1].max()) / 2.0 - v_mid
        centre = centre + (right * du + down * dv) * dist / focal
        dist = fit(centre)
    return pose_at(centre, dist)


def view_pose(
    view: str,
    box: SceneBox,
    viewport: tuple[int, int],
    extra: np.ndarray | None = None,
    head_fov_rad: float = float(np.radians(47.0)),
    frustum_depth_m: float = 0.0,
) -> CameraPose:
    """The camera of one of :data:`VIEWS`, framing ``box`` (and the ``extra`` points (M,
    3), e.g. the picture panel placed for the view) in a canvas of ``viewport`` (width,
    height) CSS pixels.

    - ``overview``: from behind and above the head (:data:`OVERVIEW_ELEVATION_RAD`),
      looking forward and down;
    - ``head``: at the rig origin looking along +z with -y up, the vertical field of view
      ``head_fov_rad`` x :data:`HEAD_FOV_MARGIN` (what the sensors see), clipping the
      frustums (``frustum_depth_m`` deep) away (:data:`HEAD_NEAR_BEYOND`);
    - ``above``: from above (-y), looking down at :data:`ABOVE_ELEVATION_RAD`, +z up on
      the screen;
    - ``side``: from the right (+x), looking left, the head on the left of the screen.

    Raises:
        ValueError: an unknown view.
    """
    forward, up = view_axes(view)
    if view == "head":
        look = (0.0, 0.0, max(box.median_z, 0.5))
        near = min(HEAD_NEAR_BEYOND * frustum_depth_m, HEAD_NEAR_MAX_M)
        fov = head_fov_rad * HEAD_FOV_MARGIN
        return CameraPose((0.0, 0.0, 0.0), look, tuple(up), fov, max(NEAR_M, near))
    pts = box.sample if extra is None else np.vstack([box.sample, extra])
    return frame_points(pts, forward, up, VIEW_FOV_RAD, viewport)


def view_axes(view: str) -> tuple[np.ndarray, np.ndarray]:
    """(forward, up) (3,) unit vectors of the camera of ``view`` (:data:`VIEWS`).

    Raises:
        ValueError: an unknown view.
    """
    up = np.array([0.0, -1.0, 0.0])
    if view in ("overview", "above"):
        e = OVERVIEW_ELEVATION_RAD if view == "overview" else ABOVE_ELEVATION_RAD
        return np.array([0.0, np.sin(e), np.cos(e)]), up
    if view == "side":
        return np.array([-1.0, 0.0, 0.0]), up
    if view == "head":
        return np.array([0.0, 0.0, 1.0]), up
    raise ValueError(f"view: expected one of {', '.join(VIEWS)}, got {view!r}")


def project(points: np.ndarray, pose: CameraPose, viewport: tuple[int, int]) -> np.ndarray:
    """(N, 2) canvas pixels (x right, y down) of ``points`` (N, 3) seen by ``pose``; NaN
    for points behind the camera."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    forward = np.asarray(pose.look_at) - np.asarray(pose.position)
    right, down, f = _basis(forward, np.asarray(pose.up, float))
    rel = p - np.asarray(pose.position)
    z = rel @ f
    focal = (viewport[1] / 2.0) / np.tan(pose.fov_rad / 2.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        u = viewport[0] / 2.0 + focal * (rel @ right) / z
        v = viewport[1] / 2.0 + focal * (rel @ down) / z
    out = np.stack([u, v], axis=1)
    out[z <= 1e-6] = np.nan
    return out


def label_boxes(
    texts: Sequence[str], anchors_px: np.ndarray, em_px: float = LABEL_EM_PX
) -> np.ndarray:
    """(N, 4) screen boxes (x0, y0, x1, y1) of labels anchored "top-center" at
    ``anchors_px`` (N, 2), from the text length (:data:`LABEL_CHAR_EM` per character)."""
    a = np.asarray(anchors_px, dtype=np.float64).reshape(-1, 2)
    w = np.array([len(t) * LABEL_CHAR_EM * em_px + 0.3 * em_px for t in texts])
    h = LABEL_LINE_EM * em_px
    return np.stack([a[:, 0] - w / 2, a[:, 1], a[:, 0] + w / 2, a[:, 1] + h], axis=1)


def overlapping_labels(boxes: np.ndarray) -> list[tuple[int, int]]:
    """Index pairs of the (N, 4) boxes that overlap (or are not finite)."""
    b = np.asarray(boxes, dtype=np.float64)
    out = []
    for i in range(len(b)):
        for j in range(i + 1, len(b)):
            if not (np.isfinite(b[i]).all() and np.isfinite(b[j]).all()):
                out.append((i, j))
                continue
            apart_x = b[i, 2] <= b[j, 0] or b[j, 2] <= b[i, 0]
            apart_y = b[i, 3] <= b[j, 1] or b[j, 3] <= b[i, 1]
            if not (apart_x or apart_y):
                out.append((i, j))
    return out
