"""The rig and the rig file: round trips, every malformed case, derived transforms."""

from __future__ import annotations

import copy
import dataclasses
import itertools
import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
import yaml

from tests.support import OPENCV_LEFT_9X6
from trifuse.app.sources.sim.head import default_rig
from trifuse.app.storage.rigfile import load_rig, save_rig
from trifuse.calib.camera import MAX_DISTORTION_TERM, Intrinsics, corner_radius
from trifuse.calib.diagnosis import FIELD_OF_VIEW_DEG, MAX_ASPECT_DEVIATION
from trifuse.calib.errors import RigError
from trifuse.calib.radiometry import Radiometry
from trifuse.calib.rig import (
    Eye,
    Rig,
    Sensor,
    check_physical,
    rig_from_dict,
    rig_from_yaml,
    rig_to_dict,
    rig_to_yaml,
)
from trifuse.calib.transforms import invert, make_T

BASE = rig_to_dict(default_rig())


# -- round trips -------------------------------------------------------------------------------


def test_yaml_round_trip_is_exact() -> None:
    rig = default_rig()
    text = rig_to_yaml(rig)
    again = rig_from_yaml(text)
    assert again == rig
    assert rig_to_yaml(again) == text
    assert rig_to_dict(again) == BASE


def test_round_trip_keeps_optional_blocks() -> None:
    d = copy.deepcopy(BASE)
    nodes = [[0.001 * (r - c) for c in range(23)] for r in range(19)]
    block = {
        "model": "trifuse-range/1",
        "distance": {"start_m": 0.5, "step_m": 0.25, "coeffs_m": [0.03, 0.02, 0.01, 0.02, 0.03]},
        "offset": {"step_px": 8, "nodes_m": nodes},
        "amplitude": {"ref": 1500.0, "log_range": [-1.0, 1.0], "coeffs_m": [0.004, -0.001]},
    }
    d["sensors"]["tof"]["range_correction"] = block
    d["sensors"]["thermal_left"]["radiometry"] = {"gain": 1.02, "offset_k": -0.3}
    d["sensors"]["ccd_left"]["uncertainty"] = {"fx": 0.4, "T_rig_sensor": {"t_m": [1e-4] * 3}}
    rig = rig_from_dict(d)
    assert rig["tof"].range_correction.to_dict() == block
    assert rig_from_yaml(rig_to_yaml(rig)) == rig
    assert rig != default_rig()


def test_file_round_trip(tmp_path: Path) -> None:
    first = tmp_path / "first" / "rig.yaml"
    second = tmp_path / "second.yaml"
    assert save_rig(first, default_rig()) == first
    loaded = load_rig(first)
    assert loaded == default_rig()
    save_rig(second, loaded)
    assert load_rig(second) == loaded
    assert second.read_text(encoding="utf-8") == first.read_text(encoding="utf-8")


def test_save_refuses_to_overwrite(tmp_path: Path) -> None:
    path = tmp_path / "rig.yaml"
    path.write_text("precious", encoding="utf-8")
    with pytest.raises(FileExistsError, match="refusing to overwrite"):
        save_rig(path, default_rig())
    assert path.read_text(encoding="utf-8") == "precious"
    save_rig(path, default_rig(), overwrite=True)
    assert load_rig(path) == default_rig()
    assert [p.name for p in tmp_path.iterdir()] == ["rig.yaml"]  # no temporary left behind


def test_load_errors_start_with_the_path(tmp_path: Path) -> None:
    path = tmp_path / "rig.yaml"
    bad = copy.deepcopy(BASE)
    bad["sensors"]["ccd_left"]["intrinsics"]["fx"] = -1.0
    path.write_text(yaml.safe_dump(bad), encoding="utf-8")
    with pytest.raises(RigError, match=rf"^{path}: sensor 'ccd_left': field 'intrinsics\.fx'"):
        load_rig(path)
    with pytest.raises(RigError, match=rf"^{tmp_path / 'missing.yaml'}: cannot read rig file"):
        load_rig(tmp_path / "missing.yaml")


# -- malformed rig files -----------------------------------------------------------------------


def _set(*path: Any, value: Any) -> Callable[[dict], None]:
    def mutate(d: dict) -> None:
        for key in path[:-1]:
            d = d[key]
        d[path[-1]] = value

    return mutate


def _del(*path: Any) -> Callable[[dict], None]:
    def mutate(d: dict) -> None:
        for key in path[:-1]:
            d = d[key]
        del d[path[-1]]

    return mutate


def _pose(sensor: str, change: Callable[[np.ndarray], None]) -> Callable[[dict], None]:
    def mutate(d: dict) -> None:
        T = np.array(d["sensors"][sensor]["T_rig_sensor"])
        change(T)
        d["sensors"][sensor]["T_rig_sensor"] = T.tolist()

    return mutate


def _scale(T: np.ndarray) -> None:
    T[:3, :3] *= 1.05


def _shear(T: np.ndarray) -> None:
    T[0, 1] += 0.1


def _reflect(T: np.ndarray) -> None:
    T[:3, 2] *= -1.0


def _last_row(T: np.ndarray) -> None:
    T[3] = [0.0, 0.0, 0.0, 2.0]


def _stringify(d: dict) -> None:
    T = d["sensors"]["ccd_left"]["T_rig_sensor"]
    d["sensors"]["ccd_left"]["T_rig_sensor"] = [[str(x) for x in row] for row in T]


S = r"sensor '{}': "
F = r"sensor '{}': field '{}': "
NOT_RIGID = r"sensor '{}': field 'T_rig_sensor': not a rigid transform: "


def case(id_: str, mutate: Callable[[dict], None], match: str, *marks: Any) -> Any:
    return pytest.param(mutate, match, id=id_, marks=marks)


MALFORMED = [
    # missing keys
    *(
        case(
            f"missing-{key}",
            _del("sensors", "ccd_left", key),
            S.format("ccd_left") + rf"missing key\(s\) \['{key}'\]",
        )
        for key in ("modality", "image_size", "intrinsics", "distortion", "T_rig_sensor")
    ),
    *(
        case(f"missing-top-{key}", _del(key), rf"^rig file: missing key\(s\) \['{key}'\]")
        for key in ("format", "reference", "sensors")
    ),
    case(
        "missing-intrinsics-cy",
        _del("sensors", "thermal_left", "intrinsics", "cy"),
        F.format("thermal_left", "intrinsics") + r"missing key\(s\) \['cy'\]",
    ),
    case(
        "missing-eye-role",
        _del("eyes", "left", "thermal"),
        r"field 'eyes\.left': missing key\(s\) \['thermal'\]",
    ),
    # wrong shapes
    case(
        "T-3x4",
        _set("sensors", "ccd_right", "T_rig_sensor", value=np.eye(4)[:3].tolist()),
        F.format("ccd_right", "T_rig_sensor") + "expected a 4x4 list of numbers",
    ),
    case(
        "T-ragged",
        _set("sensors", "ccd_right", "T_rig_sensor", value=[[1, 0], [0, 1, 0]]),
        F.format("ccd_right", "T_rig_sensor") + "expected a 4x4 list of numbers",
    ),
    case(
        "image_size-3",
        _set("sensors", "tof", "image_size", value=[176, 144, 3]),
        F.format("tof", "image_size") + r"expected \[width, height\] as two positive integers",
    ),
    case(
        "image_size-zero",
        _set("sensors", "tof", "image_size", value=[176, 0]),
        F.format("tof", "image_size") + "expected",
    ),
    case(
        "image_size-huge",  # allocating for it would take gigabytes before any check
        _set("sensors", "ccd_left", "image_size", value=[20000, 20000]),
        F.format("ccd_left", "image_size") + "20000x20000 is 400 megapixels; expected at most 50",
    ),
    case(
        "image_size-float",
        _set("sensors", "tof", "image_size", value=[176.0, 144]),
        F.format("tof", "image_size") + "expected",
    ),
    case(
        "distortion-3",
        _set("sensors", "thermal_right", "distortion", value=[0.1, 0.0, 0.0]),
        F.format("thermal_right", "distortion")
        + r"expected a list of 4, 5 or 8 numbers .*got \[0\.1",
    ),
    case(
        "distortion-not-list",
        _set("sensors", "thermal_right", "distortion", value=0.1),
        F.format("thermal_right", "distortion") + "expected a list of 4, 5 or 8 numbers",
    ),
    # non-rigid poses
    case(
        "T-scaled",
        _pose("ccd_left", _scale),
        NOT_RIGID.format("ccd_left") + "rotation block is not orthonormal",
    ),
    case(
        "T-shear",
        _pose("ccd_left", _shear),
        NOT_RIGID.format("ccd_left") + "rotation block is not orthonormal",
    ),
    case(
        "T-reflection",
        _pose("thermal_left", _reflect),
        NOT_RIGID.format("thermal_left") + r"rotation block is a reflection \(det = -1",
    ),
    case(
        "T-last-row",
        _pose("ccd_right", _last_row),
        NOT_RIGID.format("ccd_right") + r"last row must be \[0, 0, 0, 1\]",
    ),
    case(
        "T-nan",
        _set("sensors", "ccd_right", "T_rig_sensor", 0, 3, value=float("nan")),
        F.format("ccd_right", "T_rig_sensor") + "expected a finite number, got nan",
    ),
    # unknown keys
    case("unknown-top", _set("serial", value="A123"), r"^rig file: unknown key\(s\) \['serial'\]"),
    case(
        "unknown-sensor-key",
        _set("sensors", "tof", "serial", value="A123"),
        S.format("tof") + r"unknown key\(s\) \['serial'\]",
    ),
    case(
        "unknown-intrinsics-key",
        _set("sensors", "ccd_left", "intrinsics", "skew", value=0.0),
        F.format("ccd_left", "intrinsics") + r"unknown key\(s\) \['skew'\]",
    ),
    case(
        "unknown-eye-key",
        _set("eyes", "left", "tof", value="tof"),
        r"field 'eyes\.left': unknown key\(s\) \['tof'\]",
    ),
    # focal lengths
    case(
        "fx-negative",
        _set("sensors", "ccd_left", "intrinsics", "fx", value=-1333.0),
        F.format("ccd_left", "intrinsics.fx") + "focal length must be positive, got -1333.0",
    ),
    case(
        "fy-zero",
        _set("sensors", "thermal_right", "intrinsics", "fy", value=0),
        F.format("thermal_right", "intrinsics.fy") + "focal length must be positive, got 0.0",
    ),
    case(
        "fx-nan",
        _set("sensors", "tof", "intrinsics", "fx", value=float("nan")),
        F.format("tof", "intrinsics.fx") + "expected a finite number",
    ),
    # physical bounds: each refused naming the sensor, the field, its value and the bound
    case(
        "fx-1e300",
        _set("sensors", "ccd_left", "intrinsics", "fx", value=1e300),
        F.format("ccd_left", "intrinsics.fx") + r"1e\+300 px gives a field of view of 7\.334e-296 "
        r"degrees across the 1280-pixel width; expected 0\.1 to 179 degrees \(fx from 5\.585 to "
        r"7\.334e\+05 px\)",
    ),
    case(
        "fy-tiny",
        _set("sensors", "thermal_right", "intrinsics", "fy", value=1e-3),
        F.format("thermal_right", "intrinsics.fy") + r"0\.001 px gives a field of view of 180 "
        "degrees across the 288-pixel height",
    ),
    case(
        "cx-far",
        _set("sensors", "tof", "intrinsics", "cx", value=1e6),
        F.format("tof", "intrinsics.cx")
        + r"1e\+06 px; expected -176\.5 to 351\.5 px \(at most 1 image width outside the image, "
        r"or 30 degrees off the image centre's direction\)",
    ),
    case(
        "cy-far",
        _set("sensors", "tof", "intrinsics", "cy", value=-145.0),
        F.format("tof", "intrinsics.cy") + r"-145 px; expected -144\.5 to 287\.5 px",
    ),
    case(
        "k1-1e300",
        _set("sensors", "ccd_right", "distortion", 0, value=1e300),
        F.format("ccd_right", "distortion")
        + r"k1 = 1e\+300 makes a term of 3\.61e\+299 at the image's "
        r"farthest corner \(normalised radius 0\.601\); expected at most 1e\+06 \(\|k1\| at most "
        r"2\.769e\+06\)",
    ),
    case(
        "k6-rational",
        _set("sensors", "ccd_right", "distortion", value=[0.1, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, -3e7]),
        F.format("ccd_right", "distortion")
        + r"k6 = -3e\+07 makes a term of 1\.41e\+06 .* \(\|k6\| "
        r"at most 2\.123e\+07\)",
    ),
    case(
        "image_size-1x1",
        _set("sensors", "tof", "image_size", value=[1, 1]),
        F.format("tof", "image_size") + "1x1; expected at least 8 pixels each way",
    ),
    case(
        "image_size-thin",
        _set("sensors", "ccd_left", "image_size", value=[7, 960]),
        F.format("ccd_left", "image_size") + "7x960; expected at least 8 pixels each way",
    ),
    # non-numeric values
    case(
        "fx-string",
        _set("sensors", "tof", "intrinsics", "fx", value="165.5"),
        F.format("tof", "intrinsics.fx") + "expected a number, got '165.5'",
    ),
    case(
        "cx-null",
        _set("sensors", "tof", "intrinsics", "cx", value=None),
        F.format("tof", "intrinsics.cx") + "expected a number, got None",
    ),
    case(
        "cy-bool",
        _set("sensors", "tof", "intrinsics", "cy", value=True),
        F.format("tof", "intrinsics.cy") + "expected a number, got True",
    ),
    case(
        "distortion-string",
        _set("sensors", "ccd_right", "distortion", 1, value="x"),
        F.format("ccd_right", "distortion") + "expected a number, got 'x'",
    ),
    case(
        "T-word",
        _set("sensors", "ccd_left", "T_rig_sensor", 1, 1, value="one"),
        F.format("ccd_left", "T_rig_sensor") + "expected a number, got 'one'",
    ),
    case(
        "T-numeric-strings",
        _stringify,
        F.format("ccd_left", "T_rig_sensor") + "expected a number, got '0.99980",
    ),
    case(
        "image_size-strings",
        _set("sensors", "tof", "image_size", value=["176", "144"]),
        F.format("tof", "image_size") + "expected",
    ),
    case(
        "modality-unknown",
        _set("sensors", "tof", "modality", value="lidar"),
        F.format("tof", "modality") + r"expected one of \['color', 'thermal', 'tof'\], got "
        "'lidar'",
    ),
    # structure
    case(
        "sensor-not-mapping",
        _set("sensors", "ccd_left", value=[1, 2]),
        S.format("ccd_left") + "expected a mapping, got list",
    ),
    case("sensors-empty", _set("sensors", value={}), "field 'sensors': the rig has no sensors"),
    case(
        "optional-not-mapping",
        _set("sensors", "tof", "range_correction", value=5),
        F.format("tof", "range_correction") + "expected a mapping, got int",
    ),
    case("eyes-list", _set("eyes", value=[]), "field 'eyes': expected a mapping"),
    # reference
    case(
        "reference-unknown",
        _set("reference", value="lidar"),
        r"^field 'reference': sensor 'lidar' is not in the rig",
    ),
    case(
        "reference-list",
        _set("reference", value=["tof"]),
        "field 'reference': expected a sensor name",
    ),
    case(
        "reference-not-identity",
        _set("reference", value="ccd_left"),
        F.format("ccd_left", "T_rig_sensor")
        + "the reference sensor defines the rig frame, so its pose must be the identity",
    ),
    # eyes
    case(
        "eye-unknown-sensor",
        _set("eyes", "left", "color", value="ccd_middle"),
        r"eyes\.left\.color: unknown sensor 'ccd_middle'",
    ),
    case(
        "eye-wrong-modality",
        _set("eyes", "right", "thermal", value="ccd_right"),
        r"eyes\.right\.thermal: sensor 'ccd_right' has modality 'color', expected 'thermal'",
    ),
    case(
        "eye-tof-as-color",
        _set("eyes", "left", "color", value="tof"),
        r"eyes\.left\.color: sensor 'tof' has modality 'tof', expected 'color'",
    ),
    # format
    case(
        "format-wrong",
        _set("format", value="trifuse-rig/2"),
        r"^field 'format': expected 'trifuse-rig/1', got 'trifuse-rig/2'",
    ),
    case("format-number", _set("format", value=1), r"^field 'format': expected 'trifuse-rig/1'"),
]


@pytest.mark.parametrize(("mutate", "match"), MALFORMED)
def test_malformed_dict_raises_rig_error(mutate: Callable[[dict], None], match: str) -> None:
    d = copy.deepcopy(BASE)
    mutate(d)
    with pytest.raises(RigError, match=match):
        rig_from_dict(d)


@pytest.mark.parametrize(("mutate", "match"), MALFORMED)
def test_malformed_text_raises_rig_error(mutate: Callable[[dict], None], match: str) -> None:
    d = copy.deepcopy(BASE)
    mutate(d)
    with pytest.raises(RigError, match=match):
        rig_from_yaml(yaml.safe_dump(d, sort_keys=False))


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("format: [trifuse-rig/1\nreference: tof\n", "rig file is not valid YAML"),
        ("format: trifuse-rig/1\n\treference: tof\n", "rig file is not valid YAML"),
        ("sensors: {a: 1}\nsensors: {b: 2}\n  - x\n", "rig file is not valid YAML"),
        ("", "rig file: expected a mapping, got NoneType"),
        ("- format\n- sensors\n", "rig file: expected a mapping, got list"),
    ],
    ids=["unclosed", "tab", "bad-indent", "empty", "list"],
)
def test_invalid_yaml_text(text: str, match: str) -> None:
    with pytest.raises(RigError, match=match):
        rig_from_yaml(text)


def test_rig_constructor_validates() -> None:
    rig = default_rig()
    with pytest.raises(RigError, match="reference: sensor 'lidar' is not in the rig"):
        Rig(sensors=rig.sensors, reference="lidar")
    with pytest.raises(RigError, match=r"eyes\.x\.thermal: sensor 'tof' has modality 'tof'"):
        Rig(sensors=rig.sensors, reference="tof", eyes={"x": Eye("ccd_left", "tof")})


def test_with_sensor_replaces_one_sensor_in_a_copy() -> None:
    rig = default_rig()
    thermal = rig["thermal_left"]
    trimmed = dataclasses.replace(thermal, radiometry=Radiometry(manual_offset_k=1.5))
    new = rig.with_sensor(trimmed)
    assert new["thermal_left"] is trimmed and rig["thermal_left"] is thermal
    assert new.names == rig.names and new.reference == rig.reference and new.eyes == rig.eyes
    assert all(new[n] is rig[n] for n in rig.names if n != "thermal_left")
    assert rig_from_yaml(rig_to_yaml(new)) == new
    with pytest.raises(KeyError, match="no sensor 'lidar' in the rig"):
        rig.with_sensor(dataclasses.replace(thermal, name="lidar"))
    with pytest.raises(RigError, match=r"eyes\.left\.thermal: sensor 'thermal_left' has modality"):
        rig.with_sensor(dataclasses.replace(thermal, modality="color"))


# -- derived transforms ------------------------------------------------------------------------

# Entries of T are O(1) (rotations) and O(0.1 m) (baselines): a few ulp is below 1e-15.
T_TOL = 1e-15


def test_T_of_a_sensor_to_itself_is_identity() -> None:
    rig = default_rig()
    for name in rig.names:
        np.testing.assert_allclose(rig.T(name, name), np.eye(4), rtol=0, atol=T_TOL)


def test_T_composes_and_inverts() -> None:
    rig = default_rig()
    for a, b, c in itertools.product(rig.names, repeat=3):
        np.testing.assert_allclose(rig.T(a, b) @ rig.T(b, c), rig.T(a, c), rtol=0, atol=T_TOL)
    for a, b in itertools.product(rig.names, repeat=2):
        np.testing.assert_allclose(rig.T(a, b), invert(rig.T(b, a)), rtol=0, atol=T_TOL)


def test_T_from_the_reference_is_the_inverse_pose() -> None:
    rig = default_rig()
    np.testing.assert_array_equal(rig["tof"].T_rig_sensor, np.eye(4))
    for name in rig.names:
        T_sensor_tof = invert(rig[name].T_rig_sensor)
        np.testing.assert_allclose(rig.T(name, "tof"), T_sensor_tof, rtol=0, atol=T_TOL)
        np.testing.assert_allclose(rig.T("tof", name), rig[name].T_rig_sensor, rtol=0, atol=T_TOL)


def test_T_of_a_toy_rig_by_hand() -> None:
    cam = Intrinsics(100.0, 100.0, 50.0, 50.0)
    sensors = {
        "tof": Sensor("tof", "tof", (101, 101), cam, np.eye(4)),
        "cam": Sensor("cam", "color", (101, 101), cam, make_T(np.eye(3), [0.1, 0.0, 0.0])),
    }
    rig = Rig(sensors=sensors, reference="tof")
    # The camera sits 10 cm right of the TOF, so a TOF-frame point appears 10 cm further
    # left (x smaller) in the camera's frame.
    np.testing.assert_array_equal(rig.T("cam", "tof"), make_T(np.eye(3), [-0.1, 0.0, 0.0]))


@pytest.mark.parametrize(("dst", "src"), [("lidar", "tof"), ("tof", "lidar")])
def test_T_of_an_unknown_sensor_is_a_key_error(dst: str, src: str) -> None:
    rig = default_rig()
    with pytest.raises(KeyError, match="no sensor 'lidar' in the rig"):
        rig.T(dst, src)


def test_lookup_helpers() -> None:
    rig = default_rig()
    assert rig.names == ["tof", "ccd_left", "ccd_right", "thermal_left", "thermal_right"]
    assert rig.by_modality("thermal") == ["thermal_left", "thermal_right"]
    assert "tof" in rig
    assert "lidar" not in rig
    assert (rig["tof"].width, rig["tof"].height) == (176, 144)


def test_modality_of_a_sensor_name() -> None:
    from trifuse.calib.rig import modality_of_name

    assert modality_of_name("CCD_left") == "color" and modality_of_name("rgb") == "color"
    assert modality_of_name("LWIR_2") == "thermal" and modality_of_name("depth0") == "tof"
    assert modality_of_name("imu") is None and modality_of_name("") is None


# -- physical bounds: what calibrations produce stays loadable ---------------------------------


PHOTOS = OPENCV_LEFT_9X6
BOARD_9X6 = np.zeros((54, 3), np.float32)
BOARD_9X6[:, :2] = np.mgrid[0:9, 0:6].T.reshape(-1, 2) * 0.025
TERM_POWERS = (2, 4, 1, 1, 6, 2, 4, 6)  # of the corner radius, k1 k2 p1 p2 k3 k4 k5 k6


def _load_calibrated(K: np.ndarray, dist: np.ndarray, size: tuple[int, int]) -> Intrinsics:
    """The intrinsics of a rig file whose ccd_left holds OpenCV's result ``K``, ``dist``
    for ``size``, loaded (RigError if refused)."""
    fx, fy, cx, cy = (float(K[i, j]) for i, j in ((0, 0), (1, 1), (0, 2), (1, 2)))
    d = copy.deepcopy(BASE)
    d["sensors"]["ccd_left"].update(
        image_size=list(size),
        intrinsics={"fx": fx, "fy": fy, "cx": cx, "cy": cy},
        distortion=dist.ravel()[:8].tolist(),
    )
    return rig_from_yaml(yaml.safe_dump(d))["ccd_left"].intrinsics


def _largest_term(intr: Intrinsics, size: tuple[int, int]) -> float:
    """The largest distortion term at the image's farthest corner (what the bound limits)."""
    r = corner_radius(intr, size)
    return max(abs(c) * r**p for c, p in zip(intr.distortion, TERM_POWERS, strict=False))


def test_every_two_view_rational_calibration_of_real_photographs_loads() -> None:
    """OpenCV's rational model on every pair of OpenCV's 13 sample photographs (its least
    constrained calibrations: numerator and denominator coefficients that nearly cancel,
    up to 1.6e4) and on all 13: each result is within the physical bounds, and a rig file
    holding it loads; the largest term at the image's corner (5.9e3) is within a hundredth
    of the bound. (A bound of 1e3 on the coefficients would refuse 8 of these.)"""
    corners = []
    for photo in sorted(PHOTOS.glob("*.jpg")):
        grey = cv2.imread(str(photo), cv2.IMREAD_GRAYSCALE)
        found, c = cv2.findChessboardCorners(grey, (9, 6))
        assert found, photo
        criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 30, 1e-3)
        corners.append(cv2.cornerSubPix(grey, c, (11, 11), (-1, -1), criteria))
    views = [*itertools.combinations(range(len(corners)), 2), tuple(range(len(corners)))]
    loaded = []
    for chosen in views:
        _rms, K, dist, _r, _t = cv2.calibrateCamera(
            [BOARD_9X6] * len(chosen), [corners[i] for i in chosen], (640, 480), None, None,
            flags=cv2.CALIB_RATIONAL_MODEL,
        )  # fmt: skip
        loaded.append(_load_calibrated(K, dist, (640, 480)))
    largest = [max(map(abs, intr.distortion)) for intr in loaded]
    assert len(largest) == 79 and max(largest) > 1e4
    assert sum(k > 1e3 for k in largest) >= 5  # (8 with OpenCV 5.0.0.93)
    assert max(_largest_term(intr, (640, 480)) for intr in loaded) < MAX_DISTORTION_TERM / 100


def _telephoto_calibration(seed: int) -> tuple[np.ndarray, np.ndarray]:
    """OpenCV's rational model from two views of the 9 x 6 board by a 2-degree telephoto
    (1280 x 960, fx 36660 px), the board filling about half the image, corners with 0.5 px
    of noise: (K, distortion)."""
    rng = np.random.default_rng(seed)
    w, h, half_fov = 1280, 960, math.radians(1.0)
    f = w / (2.0 * math.tan(half_fov))
    K = np.array([[f, 0.0, (w - 1) / 2], [0.0, f, (h - 1) / 2], [0.0, 0.0, 1.0]])
    seen: list[np.ndarray] = []
    while len(seen) < 2:
        z = 0.1 / math.tan(half_fov) * rng.uniform(0.8, 1.6)
        reach = 0.3 * z * math.tan(half_fov)
        t = np.array([rng.uniform(-reach, reach) - 0.1, rng.uniform(-reach, reach) - 0.0625, z])
        uv, _ = cv2.projectPoints(BOARD_9X6.astype(np.float64), rng.normal(0, 0.4, 3), t, K, None)
        uv = uv.reshape(-1, 2)
        if (uv >= 0).all() and (uv <= (w - 1, h - 1)).all():
            seen.append((uv + rng.normal(0.0, 0.5, uv.shape)).astype(np.float32))
    _rms, K, dist, _r, _t = cv2.calibrateCamera(
        [BOARD_9X6] * 2, seen, (w, h), None, None, flags=cv2.CALIB_RATIONAL_MODEL
    )
    return K, dist


def test_what_opencv_calibrates_of_a_telephoto_loads() -> None:
    """A narrow lens's coefficients grow as its corner radius shrinks, and its principal
    point is barely observable: 40 seeded two-view calibrations of a 2-degree telephoto
    give coefficients beyond 1e6 and principal points more than an image width outside the
    image (which bounds on the coefficients and on image sizes alone would refuse), yet
    every distortion term at the image's corner stays a hundredth of the bound, the
    principal point within 10 degrees of the axis, and every result loads."""
    size = (1280, 960)
    loaded = [_load_calibrated(*_telephoto_calibration(seed), size) for seed in range(40)]
    assert max(max(map(abs, intr.distortion)) for intr in loaded) > 1e6  # (seed 9: 2.9e6)
    assert max(abs(intr.cx - 639.5) / 1280 for intr in loaded) > 1.5
    assert max(math.atan(abs(intr.cx - 639.5) / intr.fx) for intr in loaded) < math.radians(10)
    assert max(_largest_term(intr, size) for intr in loaded) < MAX_DISTORTION_TERM / 100


def test_what_the_calibration_screening_lets_through_loads() -> None:
    """calib.diagnosis lets Zhang's intrinsics through with a horizontal field of view of
    2 to 170 degrees, the principal point in the image and fy within 20 % of fx; the bounds
    of a rig file are wider, so every rig a calibration saves loads again."""
    lo, hi = FIELD_OF_VIEW_DEG
    for w, h in [(8, 8), (176, 144), (1280, 960), (480, 640)]:
        for fov in (lo, hi):
            fx = w / (2.0 * math.tan(math.radians(fov) / 2.0))
            for fy in (fx * (1 - MAX_ASPECT_DEVIATION), fx * (1 + MAX_ASPECT_DEVIATION)):
                for cx, cy in [(-0.5, -0.5), (w - 0.5, h - 0.5)]:
                    sensor = Sensor("cam", "color", (w, h), Intrinsics(fx, fy, cx, cy), np.eye(4))
                    check_physical(sensor)


def test_check_physical_refuses_a_sensor_built_in_code() -> None:
    tof = default_rig()["tof"]
    check_physical(tof)
    with pytest.raises(RigError, match=r"^sensor 'tof': field 'image_size': 1x1; expected at"):
        check_physical(dataclasses.replace(tof, image_size=(1, 1)))
    far = dataclasses.replace(tof.intrinsics, fx=1e300)
    with pytest.raises(RigError, match=r"^sensor 'tof': field 'intrinsics\.fx': 1e\+300 px"):
        check_physical(dataclasses.replace(tof, intrinsics=far))
