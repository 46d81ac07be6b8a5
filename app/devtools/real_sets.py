"""Registry of the real calibration captures in tests/data, and reading their images.

Each :class:`RealSet` names a directory under ``tests/data`` (its README and licence
beside the images), the board, the sensors and where their images are, the OpenCV
reference figures measured on it (:func:`app.devtools.opencv_figures.measure`, written
into the README) and, where the data's authors published a calibration, their figures.
:func:`load_views` reads a sensor's images as the set stores them.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from trifuse.calib.opencv_reference import CharucoTarget
from trifuse.calib.transforms import rotation_angle_deg

DATA_DIR = Path(__file__).resolve().parents[2] / "tests" / "data"


@dataclass(frozen=True)
class Checkerboard:
    """``cols x rows`` inner corners (OpenCV's pattern size), squares of ``square_m``."""

    cols: int
    rows: int
    square_m: float

    def points(self) -> np.ndarray:
        """(cols * rows, 3) board points in OpenCV's row-major order, metres."""
        c, r = np.meshgrid(np.arange(self.cols), np.arange(self.rows))
        return np.stack([c.ravel(), r.ravel(), np.zeros(c.size)], axis=1) * self.square_m

    def describe(self) -> str:
        sym = " (symmetric under a half turn)" if (self.cols + self.rows) % 2 == 0 else ""
        return (
            f"checkerboard {self.cols} x {self.rows} inner corners{sym}, "
            f"{self.square_m * 1000:g} mm squares"
        )


@dataclass(frozen=True)
class Sensor:
    """One imager of a set.

    Attributes:
        name: the sensor's name (trifuse's convention: ``ccd*``/``thermal*`` ...).
        modality: ``"color"`` or ``"thermal"``.
        files: glob (relative to the set's directory) of its images, or one video file.
        view: regular expression whose first group, searched in a file name, is the view
            id that pairs it with the other sensors' images (unused for a video: the
            frame index, 4 digits, is the view id).
        image_size: (width, height) pixels.
        max_side_px: detect on a copy downscaled to this longest side (None: full size).
    """

    name: str
    modality: str
    files: str
    view: str
    image_size: tuple[int, int]
    max_side_px: int | None = None

    @property
    def is_video(self) -> bool:
        return self.files.endswith((".mp4", ".avi", ".mkv"))


@dataclass(frozen=True)
class SensorFigures:
    """OpenCV's figures for one sensor: views with a board, of how many, and calibrateCamera."""

    found: int
    views: int
    rms_px: float
    fx: float
    fy: float
    cx: float
    cy: float
    dist: tuple[float, ...]


@dataclass(frozen=True)
class PairFigures:
    """``cv2.stereoCalibrate`` of sensor ``b`` relative to ``a`` (intrinsics fixed)."""

    a: str
    b: str
    views: int
    rms_px: float
    baseline_m: float
    rotation_deg: float


@dataclass(frozen=True)
class RealSet:
    """A real capture kept in ``tests/data/<name>`` (README.md and licence beside it).

    Attributes:
        name: the directory's name under tests/data.
        licence: the licence's name and its file in the directory.
        source: where it comes from (repository and commit).
        board: the target.
        sensors: the imagers and their files.
        pairs: (a, b) sensor pairs to stereo-calibrate.
        view_step: measure every ``view_step``-th view (sorted ids) to keep it fast.
        reference: the OpenCV figures
            :func:`~app.devtools.opencv_figures.measure` gives (also in the README).
        reference_pairs: likewise for the pairs.
        published: the authors' own calibration, flat ``"<sensor>.<field>"`` or
            ``"<a>-<b>.<field>"`` -> value (pixels, metres, degrees), and where from.
        published_source: what ``published`` comes from.
    """

    name: str
    licence: tuple[str, str]
    source: str
    board: Checkerboard | CharucoTarget
    sensors: tuple[Sensor, ...]
    pairs: tuple[tuple[str, str], ...] = ()
    view_step: int = 1
    reference: dict[str, SensorFigures] = field(default_factory=dict)
    reference_pairs: tuple[PairFigures, ...] = ()
    published: dict[str, float] = field(default_factory=dict)
    published_source: str = ""

    @property
    def path(self) -> Path:
        return DATA_DIR / self.name

    def sensor(self, name: str) -> Sensor:
        for s in self.sensors:
            if s.name == name:
                return s
        raise ValueError(
            f"set {self.name!r}: no sensor {name!r} ({[s.name for s in self.sensors]})"
        )


# -- I/O --------------------------------------------------------------------------------


def _read_image(path: Path) -> np.ndarray:
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise ValueError(f"{path}: expected an image OpenCV can read")
    if img.ndim == 3 and img.shape[2] == 4:
        img = cv2.cvtColor(img, cv2.COLOR_BGRA2RGB)
    elif img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
    return img


def sensor_files(rs: RealSet, sensor: Sensor, root: Path | None = None) -> dict[str, Path]:
    """View id -> image file of one sensor (a video's id is its file's own name)."""
    base = root or rs.path
    if sensor.is_video:
        return {"video": base / sensor.files}
    out: dict[str, Path] = {}
    for p in sorted(base.glob(sensor.files)):
        m = re.search(sensor.view, p.name)
        if m:
            out[m.group(1)] = p
    return out


def load_views(rs: RealSet, sensor: Sensor, root: Path | None = None) -> dict[str, np.ndarray]:
    """View id -> image (RGB uint8, grey, or thermal as stored), every ``view_step``-th view.

    Video frames are numbered from 0 (4 digits) in the order the file gives them.
    """
    files = sensor_files(rs, sensor, root)
    if sensor.is_video:
        cap = cv2.VideoCapture(str(files["video"]))
        frames: dict[str, np.ndarray] = {}
        k = 0
        while True:
            ok, frame = cap.read()
            if not ok:
                break
            if k % rs.view_step == 0:
                frames[f"{k:04d}"] = cv2.cvtColor(frame, cv2.COLOR_BGR2RGB)
            k += 1
        cap.release()
        if not frames:
            raise ValueError(f"{files['video']}: expected a video OpenCV can read")
        return frames
    ids = sorted(files)[:: rs.view_step]
    return {v: _read_image(files[v]) for v in ids}


def published_relative_pose(
    R_a: np.ndarray, t_a: np.ndarray, R_b: np.ndarray, t_b: np.ndarray
) -> tuple[float, float]:
    """Baseline (metres) and rotation angle (degrees) between two cameras given as
    world-to-camera ``x_cam = R x_world + t`` (caliscope's camera_array.toml)."""
    R = R_b @ R_a.T
    t = t_b - R @ t_a
    return float(np.linalg.norm(t)), rotation_angle_deg(R)


# -- the registry -----------------------------------------------------------------------


def _caliscope_published() -> dict[str, float]:
    """Focal lengths and relative poses of caliscope's camera_array.toml (values copied)."""
    fx_fy = {
        "cam_0": (903.550124089999, 907.8788668762852),
        "cam_1": (760.3305587590094, 761.0214920664032),
        "cam_2": (650.801908585405, 654.4652152401134),
        "cam_3": (639.8834321530571, 639.5401432267563),
    }
    R = {
        "cam_0": [[-0.7070716153979968, 0.5639880775931625, -0.42657611165094056],
                  [0.2085224389078015, -0.4101235314731174, -0.8878722213268985],
                  [-0.6756982486068828, -0.716739936981879, 0.17238253845677978]],
        "cam_1": [[0.6613902392467378, 0.7469219825175439, -0.06834108179715134],
                  [0.3004456891516915, -0.3473189938058137, -0.8883140798230553],
                  [-0.6872374693650716, 0.5669894783624995, -0.4541228821881946]],
        "cam_2": [[-0.23474520574867236, 0.8701987696136831, -0.43318447541531985],
                  [0.39180150339004355, -0.32313146123239816, -0.861439284397407],
                  [-0.8895989379036572, -0.3719410707688081, -0.26509162483193865]],
        "cam_3": [[-0.751264381927914, 0.464391415089646, -0.4689802149744754],
                  [0.2875117973074497, -0.409335974483884, -0.8658989700896802],
                  [-0.594086521354852, -0.785356399085387, 0.17400152746492153]],
    }  # fmt: skip
    t = {
        "cam_0": [0.17125994082321383, -0.03234536459937444, 1.208386461814154],
        "cam_1": [-0.29266714687789375, 0.028837530720896648, 0.8219194275993559],
        "cam_2": [-0.23847883889454596, 0.18461082840729343, 1.1682943900670697],
        "cam_3": [0.04220586444080891, 0.18220136998970032, 1.3701267074205434],
    }
    out: dict[str, float] = {}
    for cam, (fx, fy) in fx_fy.items():
        out[f"{cam}.fx"], out[f"{cam}.fy"] = fx, fy
    for b in ("cam_1", "cam_2", "cam_3"):
        base, rot = published_relative_pose(
            np.array(R["cam_0"]), np.array(t["cam_0"]), np.array(R[b]), np.array(t[b])
        )
        out[f"cam_0-{b}.baseline_m"], out[f"cam_0-{b}.rotation_deg"] = base, rot
    return out


def _pose2sim_published() -> dict[str, float]:
    """fx, fy, cx, cy of Pose2Sim's Calib_scene.toml (values copied)."""
    k = {
        "cam01": (1671.5012042021037, 1671.3866928599075, 564.6403499852015, 933.0074897877159),
        "cam02": (1675.7080607483433, 1675.4079150009259, 555.7798754387691, 937.7259328417255),
        "cam03": (1678.7524092974595, 1678.1875775424717, 556.0712835099544, 928.197809795709),
        "cam04": (1690.8621773209618, 1689.2410845215763, 535.7642414457736, 933.0004533663628),
    }
    names = ("fx", "fy", "cx", "cy")
    return {f"{c}.{f}": v for c, vs in k.items() for f, v in zip(names, vs, strict=True)}


_SETS = (
    RealSet(
        name="opencv-left-9x6",
        licence=("Apache-2.0", "LICENSE.opencv-Apache-2.0.txt"),
        source="OpenCV samples/data (left01-left14 without left10)",
        board=Checkerboard(9, 6, 0.025),
        sensors=(Sensor("ccd_left", "color", "left*.jpg", r"left(\d+)", (640, 480)),),
        reference={
            "ccd_left": SensorFigures(
                13,
                13,
                0.339415,
                532.354,
                532.54,
                342.423,
                235.042,
                (-0.273462, -0.0385304, 0.0011263, -0.000175409, 0.285173),
            ),
        },
    ),
    RealSet(
        name="czha626-thermal-visible",
        licence=("BSD-3-Clause", "LICENSE.BSD-3-Clause.txt"),
        source="github czha626/Thermal-Camera-Calibration-and-Textured-BIM @ 840b019",
        board=Checkerboard(6, 5, 0.1),
        sensors=(
            Sensor("thermal", "thermal", "thermal/Img*.jpg", r"Img(\d+)", (640, 480)),
            Sensor("visible", "color", "visible/Img*.jpg", r"Img(\d+)", (4056, 3040), 1000),
        ),
        pairs=(("visible", "thermal"),),
        reference={
            "thermal": SensorFigures(
                12,
                12,
                0.444881,
                664.382,
                666.073,
                328.26,
                261.314,
                (-0.401006, 0.520154, -0.00294165, -0.000244339, -0.258817),
            ),
            "visible": SensorFigures(
                12,
                12,
                1.47847,
                3029.86,
                3033.48,
                2051.59,
                1542.43,
                (0.0551634, -0.426305, 0.0044365, 0.00308132, 1.35642),
            ),
        },
        reference_pairs=(PairFigures("visible", "thermal", 12, 4.36101, 0.024727, 2.22325),),
    ),
    RealSet(
        name="boofcv-bumblebee2-chess",
        licence=("CC-BY-4.0", "LICENSE.BoofCV-Data-CC-BY-4.0.txt"),
        source="github lessthanoptimal/BoofCV-Data @ cc6d8ad, "
        "example/calibration/stereo/Bumblebee2_Chess",
        board=Checkerboard(4, 6, 0.030),
        sensors=(
            Sensor("ccd_left", "color", "left*.jpg", r"left(\d+)", (640, 480)),
            Sensor("ccd_right", "color", "right*.jpg", r"right(\d+)", (640, 480)),
        ),
        pairs=(("ccd_left", "ccd_right"),),
        reference={
            "ccd_left": SensorFigures(
                11,
                11,
                0.144556,
                527.859,
                530.036,
                312.808,
                243.354,
                (-0.372512, 0.246684, 0.00142344, -0.000345721, -0.127067),
            ),
            "ccd_right": SensorFigures(
                11,
                11,
                0.130687,
                525.011,
                527.187,
                321.569,
                245.654,
                (-0.358321, 0.182428, 3.18513e-05, -0.00150571, -0.0403909),
            ),
        },
        reference_pairs=(PairFigures("ccd_left", "ccd_right", 11, 0.150495, 0.120869, 0.861843),),
        published={
            "ccd_left.fx": 524.6141554796689,
            "ccd_left.fy": 526.9202267407102,
            "ccd_left.cx": 312.4508572809385,
            "ccd_left.cy": 247.40163214599613,
            "ccd_right.fx": 526.437309515818,
            "ccd_right.fy": 528.6524795626539,
            "ccd_right.cx": 318.40405668073225,
            "ccd_right.cy": 245.93504188705572,
            "ccd_left-ccd_right.baseline_m": 0.1200507,
        },
        published_source="stereo.yaml beside the images (BoofCV's calibration: 2 radial "
        "terms, no tangential; rightToLeft translation 120.04, 0.90, -0.91 mm)",
    ),
    RealSet(
        name="caliscope-charuco-4cam",
        licence=("BSD-2-Clause", "LICENSE.caliscope-BSD-2-Clause.txt"),
        source="github mprib/caliscope @ ddda95b, tests/sessions/post_optimization",
        board=CharucoTarget((4, 5), 0.054, 0.75 * 0.054, "DICT_4X4_1000", inverted=True),
        sensors=tuple(
            Sensor(f"cam_{i}", "color", f"cam_{i}.mp4", "", (1280, 720)) for i in range(4)
        ),
        pairs=(("cam_0", "cam_1"), ("cam_0", "cam_2"), ("cam_0", "cam_3")),
        reference={
            "cam_0": SensorFigures(
                57,
                57,
                0.212558,
                889.203,
                900.653,
                620.657,
                335.686,
                (-0.384252, 0.72074, 0.000646806, 0.00749972, -2.90679),
            ),
            "cam_1": SensorFigures(
                48,
                57,
                0.209147,
                769.58,
                766.706,
                640.63,
                353.783,
                (0.0406503, 0.129039, -0.00630559, 0.00295585, -0.690824),
            ),
            "cam_2": SensorFigures(
                50,
                57,
                0.204078,
                682.9,
                679.414,
                632.526,
                399.685,
                (0.262746, -1.24948, 0.000506001, -0.00435064, 3.19936),
            ),
            "cam_3": SensorFigures(
                40,
                57,
                0.276572,
                629.237,
                621.535,
                698.127,
                314.197,
                (0.204759, 0.0378159, -0.0199999, 0.0244712, -0.68017),
            ),
        },
        reference_pairs=(
            PairFigures("cam_0", "cam_1", 48, 1.21634, 1.14115, 91.3308),
            PairFigures("cam_0", "cam_2", 50, 0.48686, 0.530687, 34.5334),
            PairFigures("cam_0", "cam_3", 40, 0.600814, 0.428638, 6.51597),
        ),
        published=_caliscope_published(),
        published_source="camera_array.toml beside the videos (caliscope's calibration: "
        "intrinsics from another recording of the same cameras, poses from its bundle "
        "adjustment on these videos)",
    ),
    RealSet(
        name="pose2sim-4cam-checker",
        licence=("BSD-3-Clause", "LICENSE.pose2sim-BSD-3-Clause.txt"),
        source="github perfanalytics/pose2sim @ eca0229, "
        "Pose2Sim/Demo_SinglePerson/calibration/intrinsics",
        board=Checkerboard(4, 7, 0.060),
        # Each camera filmed the board on its own (not at the same moments): no shared view.
        sensors=tuple(
            Sensor(f"cam{c}", "color", f"cam{c}/cam{c}_*.jpg", r"(cam\d+_\d+)", (1088, 1920))
            for c in ("01", "02", "03", "04")
        ),
        reference={
            "cam01": SensorFigures(
                7,
                7,
                0.941015,
                1680.03,
                1680.14,
                570.722,
                939.714,
                (-0.0918183, 0.568758, -0.000152337, 0.00209366, -1.49206),
            ),
            "cam02": SensorFigures(
                6,
                7,
                1.13936,
                1671.65,
                1668.95,
                556.554,
                944.416,
                (-0.0607826, 0.250669, -0.00259766, 0.00120323, -0.602007),
            ),
            "cam03": SensorFigures(
                6,
                7,
                0.924985,
                1680.05,
                1679.88,
                553.205,
                924.835,
                (0.0456087, -1.33822, -0.00169708, -0.00106813, 5.85772),
            ),
            "cam04": SensorFigures(
                6,
                7,
                1.72674,
                1694.07,
                1693.95,
                519.597,
                939.854,
                (-0.0559704, 0.212592, 0.00168622, -0.00130956, -0.303101),
            ),
        },
        published=_pose2sim_published(),
        published_source="Calib_scene.toml beside the images (Pose2Sim's calibration of these "
        "images: classic detector, cornerSubPix 11 x 11, calibrateCamera with k3 fixed)",
    ),
)
REAL_SETS: dict[str, RealSet] = {rs.name: rs for rs in _SETS}
"""The sets in tests/data, by name."""

UNCOMMITTED_SETS: dict[str, RealSet] = {
    # No licence: measured from a copy outside the checkout (--root), never committed.
    "vimslab-thermal-calibration": RealSet(
        name="vimslab-thermal-calibration",
        licence=("none (all rights reserved)", ""),
        source="github VimsLab/thermal_calibration @ 997c861, test_imgs/",
        board=Checkerboard(9, 6, 0.0231),
        sensors=(
            Sensor("ccd_left", "color", "13020556/*.ppm", r"(\d+)\.ppm", (1280, 960)),
            Sensor("ccd_right", "color", "13232653/*.ppm", r"(\d+)\.ppm", (1280, 960)),
            Sensor("thermal_left", "thermal", "5003/*.pgm", r"(\d+)\.pgm", (640, 480)),
            Sensor("thermal_right", "thermal", "5270/*.pgm", r"(\d+)\.pgm", (640, 480)),
        ),
        pairs=(
            ("ccd_left", "ccd_right"),
            ("thermal_left", "thermal_right"),
            ("ccd_left", "thermal_left"),
        ),
    ),
    "harunrk-lepton35-zed2i": RealSet(
        name="harunrk-lepton35-zed2i",
        licence=("none (all rights reserved)", ""),
        source="github harunrk/ZED_2i_and_lepton_3.5_calibration @ 54a0f79",
        board=Checkerboard(4, 6, 0.055),
        sensors=(
            Sensor("ccd_left", "color", "zed_images/zed_*.png", r"zed_(\d+_\d+)", (1280, 720)),
            Sensor(
                "thermal_left",
                "thermal",
                "thermal_images/thermal_*.png",
                r"thermal_(\d+_\d+)",
                (120, 160),
            ),
        ),
        pairs=(("ccd_left", "thermal_left"),),
    ),
}
